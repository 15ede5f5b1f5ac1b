"""What the OpenVINO engine needs of a checkpoint, remembered beside its cache so that a warm run never builds the
torch model.

On a warm engine cache (:mod:`aerialmtl.inference.engine_cache`) a prediction needs of the checkpoint only its
metadata (:class:`~aerialmtl.formats.checkpoint.ModelMeta`), the names of the model's outputs, the text of its
configuration (part of the cache key), its dropout layers (the MC masks' shapes) and its fingerprint (provenance
and the cache key). Loading the checkpoint with ``torch.load``, checking every weight for NaN, building the
D3-Net and loading its state dict cost about a CPU second for the paper's DenseNet-121 (bench/RESULTS.md,
"predict end to end on CPUs"); this module keeps that information in a small *record*:

* written by the run that loaded the checkpoint (:func:`write_record`), under
  ``<cache root>/records/<key>.record``, where the key hashes the checkpoint's SHA-256 (of its bytes), the
  aerialmtl version and :data:`RECORD_VERSION`; the entry carries its own checksum like every cache entry
  (:func:`~aerialmtl.stores.pack`) and is read under the stores' rule (:class:`~aerialmtl.stores.Store`: a
  damaged, empty, foreign or non-regular record is removed with a warning and written again);
* read by later runs after hashing the checkpoint's bytes (:func:`~aerialmtl.formats.checkpoint.file_sha256`):
  same bytes, same record.
  The record is trusted only for bytes that the run that wrote it loaded and checked (``read_checkpoint``
  refuses NaN weights and damaged files before a record can exist), so the warm path refuses nothing the
  cold one would accept and accepts nothing it would refuse.

The model itself stays available (:class:`CheckpointModel`): whatever needs it (a compiled model missing from
the cache, the fallback to the torch engine) loads it then, and the bytes loaded must hash to the same
fingerprint, or the run stops (the file was replaced while it ran).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import nn

from aerialmtl._version import __version__
from aerialmtl.errors import CheckpointError
from aerialmtl.formats import checkpoint  # read_model looked up at call time: tests stop a load by patching it
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.models.d3net import D3Net
from aerialmtl.models.mc_dropout import DropoutSite, dropout_sites
from aerialmtl.stores import Store

#: Version of the record's content (a change makes older records unused, never misread).
RECORD_VERSION = 1
#: Folder of the records under the OpenVINO cache root.
RECORDS = "records"


@dataclass(frozen=True)
class ModelRecord:
    """What a prediction on the OpenVINO engine needs of a checkpoint besides the compiled model.

    Attributes:
        meta: the checkpoint's metadata.
        outputs: the model's output names, in order (:attr:`~aerialmtl.models.d3net.D3Net.outputs`).
        cfg_text: ``str()`` of the built model's configuration (part of the engine cache's key).
        sites: the decoder's seedable dropout layers (:func:`~aerialmtl.models.mc_dropout.dropout_sites`).
    """

    meta: ModelMeta
    outputs: tuple[str, ...]
    cfg_text: str
    sites: tuple[DropoutSite, ...]

    def to_json(self) -> bytes:
        """The record as JSON bytes."""
        return json.dumps({"version": RECORD_VERSION, "meta": self.meta.to_dict(), "outputs": list(self.outputs),
                           "cfg": self.cfg_text,
                           "sites": [[s.p, s.channels, s.stride, s.channelwise] for s in self.sites]},
                          sort_keys=True).encode()

    @classmethod
    def from_json(cls, data: bytes) -> ModelRecord:
        """A record from :meth:`to_json`'s bytes (``ValueError``/``KeyError``/``TypeError`` when they are not one)."""
        raw: dict[str, Any] = json.loads(data)
        if raw.get("version") != RECORD_VERSION:
            raise ValueError(f"record version {raw.get('version')!r}")
        sites = tuple(DropoutSite(float(p), int(c), int(s), bool(cw)) for p, c, s, cw in raw["sites"])
        return cls(ModelMeta.from_dict(raw["meta"]), tuple(str(o) for o in raw["outputs"]), str(raw["cfg"]), sites)


def record_path(digest: str, root: Path) -> Path:
    """Where the record of the checkpoint with fingerprint ``digest`` lives under cache root ``root``."""
    key = hashlib.blake2b(f"{digest}|{__version__}|{RECORD_VERSION}".encode(), digest_size=12).hexdigest()
    return root / RECORDS / f"{key}.record"


def any_record(root: Path) -> bool:
    """Whether cache root ``root`` holds any checkpoint record (a cold cache holds none: no checkpoint needs
    hashing to look one up).
    """
    return any((root / RECORDS).glob("*.record"))


def read_record(digest: str, root: Path) -> ModelRecord | None:
    """The record of fingerprint ``digest``, or ``None`` (missing, unreadable or damaged).

    A damaged record is removed, and the run that loads the checkpoint writes it again.
    """
    path = record_path(digest, root)
    store = _store(path)
    found = store.read(path.name)
    if found is None:
        return None
    try:
        (payload,) = found
        return ModelRecord.from_json(payload)
    except (ValueError, KeyError, TypeError):
        store.problem(path, "not a record of this version")
        return None


def _store(path: Path) -> Store:
    """The store of the records (the folder of ``path``)."""
    return Store(path.parent, what="cached checkpoint record", env="AERIALMTL_OPENVINO_CACHE", kind="OpenVINO")


def make_record(model: nn.Module, meta: ModelMeta) -> ModelRecord | None:
    """The record of a loaded D3-Net, or ``None`` when it cannot stand for the model.

    It cannot for another model class, or for metadata that would not come back equal from JSON: such
    checkpoints are always loaded.
    """
    if type(model) is not D3Net:
        return None
    record = ModelRecord(meta, tuple(model.outputs), str(model.cfg),
                         tuple(dropout_sites(model, meta.model.in_channels)))
    try:
        if ModelRecord.from_json(record.to_json()) != record or ModelMeta.from_dict(meta.to_dict()) != meta:
            return None
    except (ValueError, KeyError, TypeError):
        return None
    return record


def write_record(digest: str, record: ModelRecord, root: Path) -> None:
    """Store ``record`` for fingerprint ``digest`` (whole, through a staging file).

    A folder that cannot be written is skipped with the stores' one warning per folder.
    """
    path = record_path(digest, root)
    _store(path).write(path.name, [record.to_json()])


class CheckpointModel:
    """The model of a checkpoint file, standing in for it until something needs the weights.

    Args:
        path: the checkpoint file.
        digest: the fingerprint of its bytes when the record was found
            (:func:`~aerialmtl.formats.checkpoint.file_sha256`).
        record: its record (:func:`read_record`).
    """

    def __init__(self, path: str | Path, digest: str, record: ModelRecord) -> None:
        self.path, self.digest, self.record = Path(path), digest, record
        self._model: nn.Module | None = None

    @property
    def outputs(self) -> tuple[str, ...]:
        """The model's output names, in order (as the loaded model's ``outputs``)."""
        return self.record.outputs

    @property
    def cfg(self) -> str:
        """The text of the loaded model's configuration (as ``str(model.cfg)``)."""
        return self.record.cfg_text

    @property
    def loaded(self) -> bool:
        """Whether the weights have been loaded."""
        return self._model is not None

    def get(self) -> nn.Module:
        """The model, loaded on first call.

        Raises:
            CheckpointError: the file no longer holds the bytes this run started with (it was replaced while
                the run went on), or it cannot be loaded.
        """
        if self._model is None:
            model, _, digest = checkpoint.read_model(self.path)
            if digest != self.digest:
                raise CheckpointError(
                    f"checkpoint '{self.path}' changed while this run used it ({self.digest} when it started, "
                    f"{digest} now); re-run when the file is no longer being written or replaced")
            self._model = model
        return self._model


def resolve_model(model: nn.Module | CheckpointModel) -> nn.Module:
    """``model`` itself, or the loaded model of a :class:`CheckpointModel`."""
    return model.get() if isinstance(model, CheckpointModel) else model


__all__ = ["RECORD_VERSION", "CheckpointModel", "ModelRecord", "any_record", "make_record", "read_record",
           "record_path", "resolve_model", "write_record"]
