"""``train --init CKPT``: start a run from the weights of an existing aerialmtl checkpoint, or of a pretrained
start shipped with the package (``--init NAME``, :mod:`aerialmtl.formats.starts`) (fine-tuning).

What is loaded: every tensor of the new model whose name and shape the checkpoint has (encoder, shared
decoder, BatchNorm statistics, and the task heads that still mean the same thing). A task head is
initialised afresh, with one warning naming it and why, when the checkpoint has no such task or, for
``classes``, when its class scheme differs (another number of classes, or the same number with other
classes or codes: index k would change meaning). The optimizer, step counter and RNG start afresh; the
normalisation is the new tile folder's (``dataset.yaml``).

Refused with :class:`~aerialmtl.errors.CheckpointError`: other orthophoto bands (the first convolution
would read other inputs), or another architecture (the encoder/decoder shapes differ).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from aerialmtl.errors import CheckpointError
from aerialmtl.formats.checkpoint import ModelMeta, load_checkpoint
from aerialmtl.formats.starts import resolve_start
from aerialmtl.models.config import Architecture

#: Architecture fields that change tensor shapes or names (dropout does not).
_SHAPE_FIELDS = tuple(f.name for f in fields(Architecture) if f.name not in ("dropout", "dropout_blocks",
                                                                                "encoder_weights"))
#: The fields that describe the DenseNet encoder only: another encoder ignores them (a Lite0 start made from one
#: config and a Lite0 recipe from another may carry different, unused values there).
_DENSENET_FIELDS = ("growth_rate", "block_config", "num_init_features", "bn_size", "compression")


def _shape_fields(old: Architecture, new: Architecture) -> tuple[str, ...]:
    """The fields whose difference changes the network's tensors, for this pair of architectures."""
    if old.encoder == new.encoder and not old.encoder.startswith("densenet"):
        return tuple(n for n in _SHAPE_FIELDS if n not in _DENSENET_FIELDS)
    return _SHAPE_FIELDS


@dataclass(frozen=True)
class InitReport:
    """What :func:`load_init_weights` did.

    Attributes:
        loaded: tensors copied from the checkpoint.
        reset: ``{task: reason}`` for heads initialised afresh.
    """

    loaded: int
    reset: dict[str, str]


def _bands(meta: ModelMeta) -> str:
    names = f" ({', '.join(meta.band_names)})" if meta.band_names else ""
    return f"{list(meta.bands)}{names}"


def _scheme(meta: ModelMeta) -> str:
    c = meta.classes
    return "no class scheme" if c is None else f"class scheme '{c.name}' ({c.num_classes} classes)"


def load_init_weights(model: torch.nn.Module, path: str | Path, meta: ModelMeta) -> InitReport:
    """Copy what fits from checkpoint ``path`` into ``model`` (a freshly initialised D3-Net described by ``meta``).

    ``path`` is a checkpoint file or the name of a start shipped with the package
    (:func:`~aerialmtl.formats.starts.resolve_start`); a start's float16 weights are loaded as float32.

    Warns (``UserWarning``, one line) when task heads are initialised afresh.

    Raises:
        CheckpointError: unusable checkpoint, other bands, or another architecture.
    """
    path = resolve_start(path)  # a file, or the name of a start shipped with the package
    payload, old = load_checkpoint(path)
    if tuple(old.bands) != tuple(meta.bands):
        raise CheckpointError(
            f"init: checkpoint '{path}' was trained on orthophoto bands {_bands(old)} but the tile folder has "
            f"bands {_bands(meta)}; fine-tune from a checkpoint trained on the same bands, or tile the "
            "orthophoto with the checkpoint's bands"
        )
    differ = [f"model.{n}: checkpoint {getattr(old.model, n)!r}, config {getattr(meta.model, n)!r}"
              for n in _shape_fields(old.model, meta.model) if getattr(old.model, n) != getattr(meta.model, n)]
    if differ:
        raise CheckpointError(
            f"init: checkpoint '{path}' has another architecture ({'; '.join(differ)}); set the config's model "
            "section to the checkpoint's (e.g. from its run's config.yaml)"
        )
    reset: dict[str, str] = {}
    for task in meta.model.tasks:
        if task not in old.model.tasks:
            reset[task] = "the checkpoint has no such task"
        elif task == "classes" and (old.classes.to_dict() if old.classes else None) != (
                meta.classes.to_dict() if meta.classes else None):
            reset[task] = f"the checkpoint has {_scheme(old)}, the tile folder {_scheme(meta)}"
    source = payload.get("state_dict") or {}
    own = model.state_dict()
    keep = {}
    for key, ref in own.items():
        parts = key.split(".")
        if parts[0] == "heads" and parts[1] in reset:
            continue
        val = source.get(key)
        if not isinstance(val, torch.Tensor) or tuple(val.shape) != tuple(ref.shape):
            shape = list(val.shape) if isinstance(val, torch.Tensor) else "missing"
            raise CheckpointError(
                f"init: checkpoint '{path}': tensor '{key}' is {shape}, the model needs {list(ref.shape)}; "
                "the file mixes weights and metadata of different runs; use the best.pt or last.pt of one run"
            )
        keep[key] = val
    model.load_state_dict(keep, strict=False)
    if reset:
        warnings.warn(
            f"init: loaded {len(keep)} tensors from '{path}'; initialised afresh: "
            + "; ".join(f"the {t} head ({why})" for t, why in reset.items()),
            UserWarning, stacklevel=2,
        )
    return InitReport(loaded=len(keep), reset=reset)


__all__ = ["load_init_weights", "InitReport"]
