"""Self-describing checkpoints: a checkpoint alone rebuilds the model and drives ``predict``.

A checkpoint is a ``torch.save``-d dict of plain types and tensors only (so it loads with
``torch.load(..., weights_only=True)``; a pickle that would run code is refused)::

    {
      "format": "aerialmtl-checkpoint", "format_version": 1, "aerialmtl_version": "0.1.0",
      "meta": {                      # ModelMeta.to_dict()
        "model": {...},              # ModelConfig
        "classes": {...} | None,     # ClassScheme (names, colours, codes)
        "bands": [1, 2, 3],          # 1-based band indexes of the orthophoto fed to the model
        "band_names": ["red", ...],
        "mean": [...], "std": [...], # per band, raw image units (normalisation)
        "gsd": 0.25,                 # metres per pixel the model was trained at
        "crs": "EPSG:...",           # CRS of the training data (information only)
        "normalization": "dataset",  # or "encoder": mean/std are the pretrained encoder's input scaling
        "calibration": {...} | None, # height knots + std scale fitted on validation (models.calibration)
        "familiarity": {...} | None, # encoder-feature density of the train split (models.familiarity)
        "sun": {...} | None,         # the training area's sun and shadow classifier (training.sun)
        "input_dtype": "uint8",      # data type of the training images (None: not recorded)
        "input_range": [lo, hi],     # their value range (value_envelope of the train statistics)
      },
      "state_dict": {...},           # model weights
      "train_state": {...} | None,   # optimizer, step, epoch, RNG... (for --resume)
    }
"""

from __future__ import annotations

import dataclasses
import io
import math
import pickle
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aerialmtl._version import __version__
from aerialmtl.classes import ClassScheme
from aerialmtl.config import from_dict, to_dict
from aerialmtl.errors import CheckpointError, ConfigError, NonFiniteError, cause
from aerialmtl.filesafety import atomic_write, open_regular, special_kind
from aerialmtl.formats.checkpoint_payload import MAX_CHECKPOINT_VALUES as MAX_CHECKPOINT_VALUES
from aerialmtl.formats.checkpoint_payload import check_state
from aerialmtl.formats.checkpoint_payload import expanded_values as expanded_values
from aerialmtl.formats.checkpoint_payload import first_nonfinite as first_nonfinite
from aerialmtl.io.fingerprint import content_sha256
from aerialmtl.io.oserrors import output_error
from aerialmtl.models.calibration import Calibration
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.models.encoders import feature_channels
from aerialmtl.models.familiarity import FeatureDensity
from aerialmtl.quiet import ignoring_warnings
from aerialmtl.signals import deferred
from aerialmtl.sun.record import TrainingSun

FORMAT = "aerialmtl-checkpoint"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class ModelMeta:
    """Everything besides the weights that ``predict`` needs to use a model."""

    model: ModelConfig
    classes: ClassScheme | None
    bands: tuple[int, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]
    gsd: float
    band_names: tuple[str, ...] = field(default_factory=tuple)
    crs: str | None = None
    #: where ``mean``/``std`` come from: ``dataset`` (the tile folder's train statistics) or ``encoder`` (the
    #: scaling the pretrained encoder weights were trained with, e.g. (x − 127) / 128 for EfficientNet-Lite).
    normalization: str = "dataset"
    #: height map and spread factor fitted on the validation split after training (applied by predict),
    #: ``None`` for checkpoints without one (see :mod:`aerialmtl.models.calibration`).
    calibration: Calibration | None = None
    #: numpy data type of the training images (``uint8``, ``uint16``, ``float32``...); ``None`` in checkpoints
    #: written before it was recorded (predict then checks nothing about the input's values).
    input_dtype: str | None = None
    #: the training images' value range: :func:`value_envelope` of the tile folder's train statistics
    #: (raw units, all bands); ``None`` when not recorded. Predict compares the orthophoto's with it
    #: (:mod:`aerialmtl.inference.sanity`).
    input_range: tuple[float, float] | None = None
    #: the reference heights of the train split, ``(min, max)`` in metres above ground (valid pixels);
    #: ``None`` when not recorded. Training calls a validation error far beyond them a divergence, predict a
    #: map far outside them garbage (:func:`plausible_heights`).
    height_range: tuple[float, float] | None = None
    #: density of the encoder's features on the train split, fitted after training (predict writes the
    #: ``unfamiliarity`` layer from it); ``None`` for checkpoints without one (:mod:`aerialmtl.models.familiarity`).
    familiarity: FeatureDensity | None = None
    #: the name of the pretrained start these weights are (:mod:`aerialmtl.formats.starts`): trained on synthetic
    #: scenes only, a start for fine-tuning (``train --init``), not a map of anywhere; ``None``: trained on its
    #: tile folder (a fine-tuned run's checkpoints are ``None`` again). Predict says so, and records it.
    start: str | None = None
    #: the training area's sun and shadow classifier, fitted after training (``predict --sun auto`` uses them for
    #: an orthophoto of the same flight); ``None`` for checkpoints without one (:mod:`aerialmtl.training.sun`).
    sun: TrainingSun | None = None

    def __post_init__(self) -> None:
        n = self.model.in_channels
        if not (len(self.bands) == len(self.mean) == len(self.std) == n):
            raise CheckpointError(
                f"checkpoint meta is inconsistent: model.in_channels={n} but bands={list(self.bands)}, "
                f"{len(self.mean)} means and {len(self.std)} stds"
            )
        k = self.model.num_classes
        if "classes" in self.model.tasks and (self.classes is None or self.classes.num_classes != k):
            raise CheckpointError(
                "checkpoint meta is inconsistent: the classes task needs a class scheme with "
                f"{self.model.num_classes} classes"
            )
        # `not (... > 0)` so that NaN fails too: a negative or zero std would silently scramble every input
        if not all(math.isfinite(m) for m in self.mean) or not all(0 < s < math.inf for s in self.std):
            raise CheckpointError(f"checkpoint meta is invalid: normalisation mean {list(self.mean)} must be finite "
                                  f"and std {list(self.std)} finite and > 0")
        if not 0 < self.gsd < math.inf:
            raise CheckpointError(f"checkpoint meta is invalid: gsd must be a positive pixel size in metres, got "
                                  f"{self.gsd}")
        if self.input_dtype is not None:
            try:
                np.dtype(self.input_dtype)
            except TypeError as exc:
                raise CheckpointError(f"checkpoint meta is invalid: input_dtype {self.input_dtype!r} is not a data "
                                      "type") from exc
        if self.input_range is not None and not (len(self.input_range) == 2
                                                 and -math.inf < self.input_range[0] < self.input_range[1] < math.inf):
            raise CheckpointError(f"checkpoint meta is invalid: input_range must be [low, high] with low < high, got "
                                  f"{list(self.input_range)}")
        if self.height_range is not None and not (len(self.height_range) == 2 and -math.inf < self.height_range[0]
                                                  <= self.height_range[1] < math.inf):
            raise CheckpointError(f"checkpoint meta is invalid: height_range must be [low, high] metres with low ≤ "
                                  f"high, got {list(self.height_range)}")
        if self.calibration is not None:
            self._check_calibration(self.calibration)

    def _check_calibration(self, cal: Calibration) -> None:
        """Refuse a calibration whose spreads or heights no model trained on :attr:`height_range` can need.

        A spread floor beyond the span of the heights trained on (σ = 1e30 m everywhere; :data:`SURFACE_HEIGHTS_M`
        where the range was not recorded), calibrated heights outside :func:`plausible_heights`.
        """
        low, high = plausible_heights(self.height_range)
        r = self.height_range if self.height_range is not None else SURFACE_HEIGHTS_M
        span = max(r[1] - r[0], 1.0)
        floors = [cal.std_floor, *cal.std_floors]
        if any(f > span for f in floors):
            raise CheckpointError(
                f"checkpoint meta is invalid: calibration spread floors {floors} m exceed the {span:g} m span of "
                f"{self._trained()} (a spread that large says nothing)")
        if any(not low <= y <= high for y in cal.height_y):
            raise CheckpointError(
                f"checkpoint meta is invalid: calibrated heights {list(cal.height_y)} m leave the [{low:g}, {high:g}] "
                f"m a model can predict from {self._trained()}")

    def _trained(self) -> str:
        """``heights of 0–45 m`` (or ``any surface`` where the trained range was not recorded), for messages."""
        r = self.height_range
        return "the heights of any surface" if r is None else f"the heights trained on ({r[0]:g}–{r[1]:g} m)"

    def to_dict(self) -> dict[str, Any]:
        """The metadata as plain types (stored in the checkpoint)."""
        result: dict[str, Any] = to_dict(self)
        return result

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelMeta:
        """Metadata from a checkpoint's plain dict (older keys read too)."""
        return from_dict(cls, data)


#: Heights above ground (m) no surface has: below the deepest pits, above the tallest buildings.
SURFACE_HEIGHTS_M = (-100.0, 1000.0)
#: How far beyond the trained height range (factor × its span + margin, metres) a validation error or a
#: predicted height may go before it is garbage rather than a model's mistake.
DIVERGED_SPAN_FACTOR = 10.0
DIVERGED_MARGIN_M = 100.0


def height_slack(height_range: tuple[float, float] | None) -> float:
    """Metres beyond the trained heights (:attr:`ModelMeta.height_range`) that no sane model reaches.

    The largest plausible height error (``DIVERGED_SPAN_FACTOR`` × span + ``DIVERGED_MARGIN_M``).
    """
    if height_range is None:
        return SURFACE_HEIGHTS_M[1] - SURFACE_HEIGHTS_M[0]
    return DIVERGED_SPAN_FACTOR * (height_range[1] - height_range[0]) + DIVERGED_MARGIN_M


def plausible_heights(height_range: tuple[float, float] | None) -> tuple[float, float]:
    """``(low, high)`` metres a model trained on ``height_range`` can sanely predict.

    :func:`height_slack` beyond it; :data:`SURFACE_HEIGHTS_M` when the range was not recorded.
    """
    if height_range is None:
        return SURFACE_HEIGHTS_M
    slack = height_slack(height_range)
    return height_range[0] - slack, height_range[1] + slack


def value_envelope(mean: Sequence[float], std: Sequence[float], dtype: str | None) -> tuple[float, float]:
    """Where nearly all values of images with these per-band statistics lie.

    ``(min_b(mean_b − 3 std_b), max_b(mean_b + 3 std_b))`` over bands b, clipped to the range of an integer
    ``dtype``.
    """
    lo = min(m - 3.0 * s for m, s in zip(mean, std))
    hi = max(m + 3.0 * s for m, s in zip(mean, std))
    if dtype is not None and np.dtype(dtype).kind in "ui":
        limits = np.iinfo(np.dtype(dtype))
        lo, hi = max(lo, float(limits.min)), min(hi, float(limits.max))
    return float(lo), float(hi)


def _os_error(exc: BaseException) -> OSError | None:
    """The ``OSError`` behind ``exc``.

    torch.save reports a full disk as a RuntimeError raised while handling the file object's OSError.
    """
    seen: BaseException | None = exc
    for _ in range(8):
        if seen is None:
            return None
        if isinstance(seen, OSError):
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def model_fingerprint(model: torch.nn.Module, meta: ModelMeta) -> str:
    """``sha256:<hex>`` of a model in memory: its metadata and every weight (names, shapes, dtypes, bytes).

    The fingerprint of a checkpoint file is that of its bytes
    (:func:`aerialmtl.formats.prediction.checkpoint_fingerprint`); this one is for models never saved.
    """
    import hashlib
    import json

    digest = hashlib.sha256(json.dumps(meta.to_dict(), sort_keys=True, default=str).encode())
    for name, t in model.state_dict().items():
        t = t.detach().cpu().contiguous()
        digest.update(f"{name}:{tuple(t.shape)}:{t.dtype}".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return f"sha256:{digest.hexdigest()}"


def save_checkpoint(
    path: str | Path,
    model: torch.nn.Module,
    meta: ModelMeta,
    train_state: dict[str, Any] | None = None,
) -> None:
    """Write a checkpoint atomically.

    A staging file ``.NAME.partial`` in the same folder, then a rename (:mod:`aerialmtl.io.outputs`).

    Raises:
        NonFiniteError: a weight holds NaN or ±inf (a diverged model is never written; the file at
            ``path``, if any, is unchanged).
        OutputError: the disk is full, or the folder is not writable (names ``path``; nothing is left
            at ``path`` or beside it).
    """
    _write(Path(path), {k: v.detach().cpu() for k, v in model.state_dict().items()}, meta, train_state)


def update_meta(path: str | Path, out: str | Path | None = None, **fields: Any) -> None:
    """Rewrite checkpoint ``path`` (or write it to ``out``) with ``fields`` of its :class:`ModelMeta` replaced (what
    is fitted after training: ``calibration``, ``familiarity``, ``sun``); weights and training state unchanged.

    One read and one atomic write, as :func:`save_checkpoint` (the same refusals and errors).
    """
    payload, meta = load_checkpoint(path)
    _write(Path(out or path), payload["state_dict"], dataclasses.replace(meta, **fields), payload.get("train_state"))


def _write(path: Path, state_dict: dict[str, torch.Tensor], meta: ModelMeta,
           train_state: dict[str, Any] | None) -> None:
    """:func:`save_checkpoint` of a CPU state dict."""
    bad = first_nonfinite(state_dict)
    if bad is not None:
        raise NonFiniteError(
            f"refusing to write checkpoint '{path}': weight '{bad}' holds NaN or inf (the model diverged); "
            "the previous checkpoint there, if any, is unchanged"
        )
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "aerialmtl_version": __version__,
        "meta": meta.to_dict(),
        "state_dict": state_dict,
        "train_state": train_state,
    }
    try:
        with atomic_write(path) as tmp, tmp.open("wb") as fh:  # a file object: a full disk is an OSError
            with deferred():  # a stop signal inside torch.save's C++ writer would come out as a RuntimeError
                torch.save(payload, fh)
    except (OSError, RuntimeError) as exc:
        cause = _os_error(exc)
        if cause is None:
            raise
        raise output_error(cause, path, "the checkpoint", "‹out_dir›") from exc


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> tuple[dict[str, Any], ModelMeta]:
    """Load a checkpoint safely (``weights_only=True``) and validate it.

    Returns:
        ``(payload, meta)``: the raw dict (``state_dict``, ``train_state``, ...) and the parsed meta.

    Raises:
        CheckpointError: missing, truncated/corrupt, unsafe (would execute code), or not an aerialmtl
            checkpoint; the message names the file and what to do.
    """
    payload, meta, _ = read_checkpoint(path, map_location)
    return payload, meta


def same_weights(a: str | Path, b: str | Path) -> bool:
    """Whether checkpoints ``a`` and ``b`` hold the same network: the same architecture, input normalisation and
    every weight and buffer equal (what the rest of their records say may differ).

    A run's ``best.pt`` and ``last.pt`` often do (when the last validation was the best): what is fitted on the
    network after training (the calibration) is then fitted once.
    """
    pa, ma = load_checkpoint(a)
    pb, mb = load_checkpoint(b)
    sa, sb = pa["state_dict"], pb["state_dict"]
    return ((ma.model, ma.mean, ma.std, ma.bands) == (mb.model, mb.mean, mb.std, mb.bands) and sa.keys() == sb.keys()
            and all(torch.equal(sa[k], sb[k]) for k in sa))


def bytes_fingerprint(data: bytes) -> str:
    """``sha256:<hex>`` of ``data`` (the fingerprint of a checkpoint file is that of the bytes that were loaded)."""
    import hashlib

    return f"sha256:{hashlib.sha256(data).hexdigest()}"


def file_sha256(path: str | Path) -> str:
    """:func:`bytes_fingerprint` of the bytes of file ``path``, streamed (not held in memory).

    A FIFO or device there is an ``OSError``, never waited on (:func:`aerialmtl.io.fingerprint.content_sha256`).
    """
    return f"sha256:{content_sha256(path)}"


def read_checkpoint(path: str | Path,
                    map_location: str | torch.device = "cpu") -> tuple[dict[str, Any], ModelMeta, str]:
    """:func:`load_checkpoint`, plus the fingerprint (:func:`bytes_fingerprint`) of the very bytes it parsed.

    The file is read once into memory and parsed from there, so the fingerprint describes the weights in
    use even when the file is replaced meanwhile (a training run writing a new ``best.pt``).
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a FIFO would block the read forever, a folder fail it
        raise CheckpointError(f"checkpoint '{path}' is {special_kind(path.stat().st_mode)}, not a regular file; pass "
                              "the best.pt or last.pt of a training run")
    if not path.is_file():
        raise CheckpointError(f"checkpoint '{path}' does not exist; pass the best.pt or last.pt of a training run")
    try:
        with open(open_regular(path, follow_links=True), "rb") as fh:  # replaced by a FIFO since: an error
            data = fh.read()
    except OSError as exc:
        raise CheckpointError(f"checkpoint '{path}' cannot be read ({exc.strerror or exc}); check its permissions, "
                              "or pass another checkpoint") from exc
    head = data[:4]
    if not head:
        raise CheckpointError(f"checkpoint '{path}' is empty (0 bytes); use another checkpoint or retrain")
    if head[:2] != b"PK" and head[:1] != b"\x80":  # neither torch.save's zip archive nor a pickle
        raise CheckpointError(
            f"checkpoint '{path}' is not a PyTorch checkpoint (it starts with {head!r}); pass the best.pt or "
            "last.pt written by `aerialmtl train`"
        )
    try:
        with ignoring_warnings(UserWarning):  # e.g. "Detected pickle protocol 4": the refusal below says it all
            payload = torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"checkpoint '{path}' was refused: it contains objects that would run code when loaded "
            "(only weights and plain data are accepted); use a checkpoint written by `aerialmtl train`"
        ) from exc
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        why = cause(exc)
        raise CheckpointError(
            f"checkpoint '{path}' is corrupt or truncated ({why}); use another checkpoint (e.g. last.pt "
            "instead of best.pt) or retrain"
        ) from exc
    if expanded_values(payload) > MAX_CHECKPOINT_VALUES:
        raise CheckpointError(
            f"checkpoint '{path}' holds more than {MAX_CHECKPOINT_VALUES:,} values once its shared references are "
            "expanded (lists that refer to lists, a pickle bomb; or a structure that contains itself): refused before "
            "reading it; no checkpoint aerialmtl writes comes near; use a checkpoint written by `aerialmtl train`")
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(
            f"checkpoint '{path}' is not an aerialmtl checkpoint (no '{FORMAT}' marker); "
            "use a checkpoint written by `aerialmtl train`"
        )
    version = payload.get("format_version", 0)
    if isinstance(version, bool) or not isinstance(version, int):
        raise CheckpointError(f"checkpoint '{path}' has an invalid format_version {version!r}; use a checkpoint "
                              "written by `aerialmtl train`")
    if version > FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint '{path}' has format version {payload['format_version']}, newer than this aerialmtl "
            f"({__version__}) reads; upgrade aerialmtl"
        )
    try:
        meta = ModelMeta.from_dict(payload["meta"])
    except (ConfigError, KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint '{path}' has invalid metadata: {exc}; it was not written by aerialmtl as it "
                              "is (edited or damaged): use a checkpoint written by `aerialmtl train`") from exc
    check_state(path, payload.get("state_dict"))
    return payload, meta, bytes_fingerprint(data)


def check_same_data(path: str | Path, saved: ModelMeta, current: ModelMeta) -> None:
    """Refuse to continue checkpoint ``path`` (meta ``saved``) on data described by ``current``.

    A resumed run must see the same class scheme (same codes, names and order: class index k must keep
    its meaning) and the same orthophoto bands; otherwise the weights would silently be trained towards
    other targets.

    Raises:
        CheckpointError: naming both class schemes or band lists and what to do.
    """
    old_cls = saved.classes.to_dict() if saved.classes is not None else None
    new_cls = current.classes.to_dict() if current.classes is not None else None
    if old_cls != new_cls:
        def name(c: ClassScheme | None) -> str:
            return "no class scheme" if c is None else f"class scheme '{c.name}' ({', '.join(c.names)})"

        raise CheckpointError(
            f"checkpoint '{path}' was trained with {name(saved.classes)} but the tile folder has "
            f"{name(current.classes)}; resume with the tile folder of that run (‹data_dir›), or start a new run "
            "(another ‹out_dir›, or ‹overwrite=True›)"
        )
    if tuple(saved.bands) != tuple(current.bands):
        raise CheckpointError(
            f"checkpoint '{path}' was trained on orthophoto bands {list(saved.bands)} but the tile folder has bands "
            f"{list(current.bands)}; resume with the tile folder of that run (‹data_dir›), or start a new run"
        )


def _state_dict_mismatch(expected: dict[str, torch.Tensor], got: Any) -> str | None:
    """Why ``got`` cannot be loaded into a model whose state dict is ``expected`` (``None`` when it can)."""
    if not isinstance(got, dict):
        return "it holds no state_dict"
    for key, ref in expected.items():
        if key not in got:
            return f"tensor '{key}' is missing"
        val = got[key]
        if not isinstance(val, torch.Tensor) or tuple(val.shape) != tuple(ref.shape):
            shape = list(val.shape) if isinstance(val, torch.Tensor) else type(val).__name__
            return f"tensor '{key}' has shape {shape}, the model needs {list(ref.shape)}"

    extra = [k for k in got if k not in expected]
    if extra:
        return f"unexpected tensor '{extra[0]}'"
    return None


def wrong_dtype(expected: dict[str, torch.Tensor], got: dict[str, torch.Tensor]) -> str | None:
    """The first tensor of ``got`` stored as another kind of number than the model's (``expected``), or ``None``.

    Another kind: a float weight as an integer or ``bool`` (``int8`` weights would be cast silently into other
    maps), an integer counter as a float, anything complex. A float of another width (a ``float16`` start) is
    the same kind, cast exactly enough.
    """
    for key, ref in expected.items():
        val = got.get(key)
        if not isinstance(val, torch.Tensor):
            continue
        if val.is_floating_point() != ref.is_floating_point() or val.is_complex() or \
                (val.dtype == torch.bool) != (ref.dtype == torch.bool):
            return (f"tensor '{key}' is stored as {str(val.dtype).replace('torch.', '')}, where the model's is "
                    f"{str(ref.dtype).replace('torch.', '')}")
    return None


def load_model(path: str | Path, map_location: str | torch.device = "cpu") -> tuple[torch.nn.Module, ModelMeta]:
    """Rebuild the model of checkpoint ``path`` with its weights, in eval mode.

    Returns:
        ``(model, meta)``.
    """
    model, meta, _ = read_model(path, map_location)
    return model, meta


def read_model(path: str | Path,
               map_location: str | torch.device = "cpu") -> tuple[torch.nn.Module, ModelMeta, str]:
    """:func:`load_model`, plus the fingerprint of the bytes the weights came from (:func:`read_checkpoint`)."""
    payload, meta, digest = read_checkpoint(path, map_location)
    model_cfg = meta.model
    if model_cfg.encoder_weights is not None:  # weights are in the state dict; don't look for the file
        model_cfg = ModelConfig(**{**to_dict(model_cfg), "encoder_weights": None,
                                   "tasks": tuple(model_cfg.tasks), "block_config": tuple(model_cfg.block_config)})
    model = D3Net(model_cfg)
    state = payload.get("state_dict")
    problem = _state_dict_mismatch(model.state_dict(), state)
    if problem is None and isinstance(state, dict):  # no problem: a dict of the model's tensors
        try:
            model.load_state_dict(state)
        except (RuntimeError, KeyError, TypeError) as exc:  # pragma: no cover - caught by the check above
            problem = cause(exc)
    if problem is None and isinstance(state, dict):
        wrong = wrong_dtype(model.state_dict(), state)
        if wrong is not None:
            raise CheckpointError(
                f"checkpoint '{path}': {wrong} (quantised or edited: loading would cast it silently into other "
                "maps); use the checkpoint as `train` wrote it")
    if problem is None and meta.familiarity is not None:
        density_problem = meta.familiarity.check_widths(feature_channels(model.encoder))
        if density_problem is not None:
            raise CheckpointError(
                f"checkpoint '{path}': {density_problem} (no fit writes that: the file was edited or mixes runs, and "
                "its unfamiliarity layer would be garbage); use the checkpoint as `train` wrote it, or refit the "
                "density (aerialmtl.training.familiarity.familiarize_checkpoint)")
    if problem is not None:
        scheme = f", class scheme '{meta.classes.name}' ({meta.classes.num_classes} classes)" if meta.classes else ""
        raise CheckpointError(
            f"checkpoint '{path}': its weights do not fit the model its metadata describes "
            f"({meta.model.in_channels} bands{scheme}): {problem}; the file mixes weights and metadata of "
            "different runs (e.g. another class scheme); use the best.pt or last.pt of one `aerialmtl train` run"
        )
    model.eval()
    return model.to(map_location), meta, digest
