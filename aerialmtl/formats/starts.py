"""Pretrained starts: small weights-only checkpoints shipped with the package, and their model cards.

A start is what ``aerialmtl pretrain`` exports (:func:`export_start`) — the weights of a model trained on
synthetic scenes only, for ``aerialmtl train --init NAME`` to fine-tune on a user's tile folder. It is not a
map of anywhere. Two files side by side, named after the start::

    NAME.pt     an aerialmtl checkpoint (format :mod:`aerialmtl.formats.checkpoint`) without training state,
                floating-point weights stored as float16 (or float32) to stay small (≤ MAX_BYTES),
                ``meta.start = NAME``; loads with ``torch.load(..., weights_only=True)``
    NAME.yaml   its model card (CARD_FORMAT): what it was trained on, for how long, on which machine, with
                which seed, that it is a start for fine-tuning; shaped like timm's ``pretrained_cfg``
                (input size, mean/std, classes) and torchgeo's ``Weights.meta`` (dataset, resolution, licence)

Shipped starts live in :data:`STARTS_DIR` (``aerialmtl/resources/starts/``, package data);
:func:`resolve_start` turns a ``--init`` value (a path, or the name of a shipped start) into a file.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import torch
import yaml

from aerialmtl.config import read_yaml
from aerialmtl.errors import CheckpointError
from aerialmtl.filesafety import atomic_write
from aerialmtl.formats.checkpoint import file_sha256, load_checkpoint
from aerialmtl.io.outputs import write_text_atomic

#: Folder of the starts shipped inside the package.
STARTS_DIR = Path(__file__).resolve().parents[1] / "resources" / "starts"
#: ``format`` tag of a model card.
CARD_FORMAT = "aerialmtl-start-card"
#: The largest start file the package ships (bytes).
MAX_BYTES = 30 * 1024 * 1024
START_SUFFIX, CARD_SUFFIX = ".pt", ".yaml"
#: What every card says a start is (and is not).
INTENDED_USE = ("a start for fine-tuning on your own area (`aerialmtl train --init NAME`), not a map of anywhere: "
                "trained on synthetic scenes only, its heights and classes on real orthophotos are not to be used "
                "without fine-tuning")


def shipped_starts(folder: Path | None = None) -> dict[str, Path]:
    """Name → file of the starts in ``folder`` (default :data:`STARTS_DIR`), sorted by name."""
    folder = STARTS_DIR if folder is None else folder
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.glob(f"*{START_SUFFIX}")) if p.is_file()}


def resolve_start(value: str | Path, folder: Path | None = None) -> Path:
    """The checkpoint file ``value`` means: an existing file, else the shipped start of that name.

    Raises:
        CheckpointError: neither (names the value and lists the shipped starts).
    """
    path = Path(value)
    if path.is_file():
        return path
    known = shipped_starts(folder)
    if str(value) in known:
        return known[str(value)]
    names = ", ".join(known) if known else "none in this installation"
    raise CheckpointError(f"init: '{value}' is neither a checkpoint file nor a shipped start (shipped starts: "
                          f"{names}); pass the best.pt or last.pt of a training run, or a start's name")


def card_path(start: str | Path) -> Path:
    """The model card beside start file ``start`` (``NAME.yaml``)."""
    return Path(start).with_suffix(CARD_SUFFIX)


def read_card(start: str | Path) -> dict[str, Any]:
    """The model card of start file ``start`` (``{}`` when it has none)."""
    path = card_path(start)
    if not path.is_file():
        return {}
    data = read_yaml(path)  # refuses an alias bomb before building it (:data:`aerialmtl.config.MAX_YAML_VALUES`)
    return data if isinstance(data, dict) else {}


def _serialised(state: dict[str, torch.Tensor], dtype: torch.dtype) -> int:
    """Bytes of ``state`` saved with its floating-point tensors in ``dtype``."""
    buf = io.BytesIO()
    torch.save({k: (v.to(dtype) if v.is_floating_point() else v).contiguous() for k, v in state.items()}, buf)
    return buf.tell()


def _too_large(out: Path, size: int) -> CheckpointError:
    return CheckpointError(f"start '{out}' would be {size / 2**20:.1f} MiB, more than the "
                           f"{MAX_BYTES / 2**20:.0f} MiB the package ships; export with float16 weights or a "
                           "smaller model")


def check_exportable(state: dict[str, torch.Tensor], out: str | Path, dtype: torch.dtype = torch.float16) -> None:
    """Refuse, before any training, weights whose start would exceed :data:`MAX_BYTES` (what :func:`export_start`
    refuses at the end).

    Args:
        state: the model's ``state_dict``.
        out: the start file it would be exported to (named in the message).
        dtype: storage type of floating-point weights.

    Raises:
        CheckpointError: the weights alone are larger than :data:`MAX_BYTES` (names the size and the fix).
    """
    size = _serialised(state, dtype)
    if size > MAX_BYTES:
        raise _too_large(Path(out), size)


def foreign_files(folder: str | Path, name: str) -> list[Path]:
    """The files at start ``name``'s two paths in ``folder`` (``NAME.pt``, ``NAME.yaml``) that are not a start of
    that name and its card: what exporting there would replace without having written it.
    """
    pt = Path(folder) / f"{name}{START_SUFFIX}"
    found = []
    if os.path.lexists(pt):
        try:
            ours = pt.is_file() and not pt.is_symlink() and load_checkpoint(pt)[1].start == name
        except (CheckpointError, OSError, ValueError, KeyError, RuntimeError):
            ours = False
        if not ours:
            found.append(pt)
    card = card_path(pt)
    if os.path.lexists(card):
        try:
            plain = card.is_file() and not card.is_symlink()  # never opens a FIFO or follows a link
            data = read_card(pt) if plain else None  # the bounded YAML reader
        except (OSError, ValueError, yaml.YAMLError):
            data = None
        if not (isinstance(data, dict) and data.get("format") == CARD_FORMAT and data.get("name") == name):
            found.append(card)
    return found


def export_start(checkpoint: str | Path, out: str | Path, name: str, card: dict[str, Any],
                 dtype: torch.dtype = torch.float16) -> Path:
    """Write the start ``out`` (a ``.pt`` file) and its card from ``checkpoint``: weights and metadata only.

    Args:
        checkpoint: an aerialmtl checkpoint (e.g. the ``last.pt`` of a pretraining run).
        out: the start file to write (``NAME.pt``; the card goes beside it, ``NAME.yaml``).
        name: the start's name (recorded as ``meta.start``: predict says the model is a start).
        card: the card's fields besides those written here (``name``, ``format``, ``file``, ``sha256``,
            ``size_bytes``, ``storage_dtype``, ``intended_use``).
        dtype: storage type of floating-point weights (``torch.float16`` halves the file; ``torch.float32``).

    Returns:
        The start file.

    Raises:
        CheckpointError: ``checkpoint`` is not a usable checkpoint, or the start would exceed :data:`MAX_BYTES`
            (nothing is written).
    """
    payload, meta = load_checkpoint(checkpoint)
    state = {k: (v.to(dtype) if v.is_floating_point() else v).contiguous() for k, v in payload["state_dict"].items()}
    meta_dict = meta.to_dict()
    meta_dict["start"] = name
    meta_dict["calibration"] = None  # a calibration belongs to the real validation split it was fitted on
    start = {k: v for k, v in payload.items() if k not in ("state_dict", "train_state", "meta")}
    start.update(meta=meta_dict, state_dict=state, train_state=None)
    out = Path(out)
    buf = io.BytesIO()
    torch.save(start, buf)
    if buf.tell() > MAX_BYTES:
        raise _too_large(out, buf.tell())
    with atomic_write(out) as tmp:
        tmp.write_bytes(buf.getvalue())
    full = {"format": CARD_FORMAT, "name": name, "file": out.name, "sha256": file_sha256(out),
            "size_bytes": out.stat().st_size, "storage_dtype": str(dtype).removeprefix("torch."),
            "intended_use": INTENDED_USE.replace("NAME", name), **card}
    write_text_atomic(card_path(out), yaml.safe_dump(full, sort_keys=False, allow_unicode=True, width=110))
    return out


__all__ = ["CARD_FORMAT", "INTENDED_USE", "MAX_BYTES", "STARTS_DIR", "card_path", "check_exportable", "export_start",
           "foreign_files", "read_card",
           "resolve_start", "shipped_starts"]
