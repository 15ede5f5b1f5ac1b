"""Output folders: created on demand, with an error that names the option and the fix."""

from __future__ import annotations

from pathlib import Path

from aerialmtl.errors import OutputError


def make_output_dir(path: str | Path, what: str = "output folder", option: str = "‹out_dir›") -> bool:
    """Create ``path`` (and its parents) if missing.

    Args:
        path: the folder.
        what: how the message calls it (``"run folder"``, ``"‹out_dir› folder"``, ...).
        option: the parameter that names it, as a mark (see :mod:`aerialmtl.errors`).

    Returns:
        True when this call created the folder (so a failed run may remove it again).

    Raises:
        OutputError: the folder cannot be created (a file in the way, no permission, ...).
    """
    path = Path(path)
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {what} '{path}' ({exc.strerror or exc}); choose a writable {option}") from exc
    return created


__all__ = ["make_output_dir"]
