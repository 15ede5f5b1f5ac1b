"""Operating-system errors met while writing an output, as :class:`~aerialmtl.errors.OutputError`.

A full disk, an exceeded quota, a read-only file system or a missing permission are conditions of the
user's machine, not bugs: the message names the file being written and what to do about it, e.g.::

    no space left on the device holding 'runs/a/last.pt' while writing the checkpoint; free space there or
    write to another folder (the previous file, if any, is unchanged)

Use :func:`writing` around the code that writes ``path`` (it converts ``OSError`` and GDAL/OGR write
errors), or :func:`output_error` in an ``except`` clause that already exists.
"""

from __future__ import annotations

import errno
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from aerialmtl.errors import AerialMTLError, OutputError, cause

#: errno values of a full device or an exceeded quota.
NO_SPACE = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG}
#: errno values of a write the user is not allowed to make.
NO_PERMISSION = {errno.EACCES, errno.EPERM, errno.EROFS}

#: substrings of GDAL/OGR messages (which carry no errno) that mean a full device.
_NO_SPACE_TEXT = ("no space left", "disk full", "disk is full", "not enough space", "file too large",
                  "quota exceeded")
_NO_PERMISSION_TEXT = ("permission denied", "read-only file system")


#: a device with less free space than this (bytes) counts as full when an unexplained write error occurs
NEARLY_FULL = 1024 * 1024


def _device_full(path: str | Path) -> bool:
    """Whether the device holding ``path`` (or its nearest existing parent) has almost no space left."""
    p = Path(path)
    for candidate in (p, *p.parents):
        if candidate.exists():
            try:
                return shutil.disk_usage(candidate).free < NEARLY_FULL
            except OSError:
                return False
    return False


def kind_of(exc: BaseException, path: str | Path | None = None) -> str | None:
    """``"space"``, ``"permission"`` or ``None`` for another error.

    Libraries that write through SQLite or GDAL do not always say that the disk is full (SQLite may report
    a missing table it could not create); with ``path``, an error they cannot explain counts as a full
    disk when the device holding ``path`` has less than :data:`NEARLY_FULL` bytes free.
    """
    code = getattr(exc, "errno", None)
    if code in NO_SPACE:
        return "space"
    if code in NO_PERMISSION:
        return "permission"
    text = str(exc).lower()
    if any(t in text for t in _NO_SPACE_TEXT):
        return "space"
    if any(t in text for t in _NO_PERMISSION_TEXT):
        return "permission"
    if path is not None and _device_full(path):
        return "space"
    return None


def output_error(exc: BaseException, path: str | Path, what: str, option: str = "‹out_dir›") -> OutputError:
    """The :class:`OutputError` to raise for ``exc`` met while writing ``what`` to ``path``.

    Args:
        exc: the ``OSError`` (or GDAL/OGR error) raised by the write.
        path: the file (or folder) being written.
        what: what it is, for the message (``"the checkpoint"``, ``"buildings.gpkg"``).
        option: the parameter that chooses the location, as a mark (see :mod:`aerialmtl.errors`).
    """
    kind = kind_of(exc, path)
    if kind == "space":
        return OutputError(
            f"no space left on the device holding '{path}' while writing {what}; free space there or write to "
            f"another folder (another {option}); no partial file was left at '{path}'"
        )
    if kind == "permission":
        return OutputError(
            f"not allowed to write '{path}' ({what}): permission denied or a read-only file system; choose a "
            f"folder you can write ({option}) or fix its permissions"
        )
    why = cause(getattr(exc, "strerror", None) or exc)
    return OutputError(f"could not write '{path}' ({what}): {why}; check the disk and the folder, or choose "
                       f"another {option}")


@contextmanager
def writing(path: str | Path, what: str, option: str = "‹out_dir›") -> Iterator[None]:
    """Turn an ``OSError`` (or a GDAL/OGR error about space or permissions) raised inside into an
    :class:`OutputError` naming ``path``; aerialmtl's own errors pass through unchanged.
    """
    try:
        yield
    except AerialMTLError:
        raise
    except OSError as exc:
        raise output_error(exc, path, what, option) from exc
    except Exception as exc:  # rasterio/pyogrio errors are not OSErrors; only the conditions named above
        if kind_of(exc, path) is None:
            raise
        raise output_error(exc, path, what, option) from exc


__all__ = ["NEARLY_FULL", "NO_PERMISSION", "NO_SPACE", "kind_of", "output_error", "writing"]
