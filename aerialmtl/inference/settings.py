"""Predict's settings: one frozen, validated object, built once and carried unchanged to the engines.

:class:`PredictSettings` holds every option of ``aerialmtl predict`` that decides the maps or how they are
computed (as :class:`~aerialmtl.tiling.tile.TileOptions` does for ``tile``). The CLI builds it from its
flags, the QGIS provider through the CLI, the Python API from its keywords (:meth:`PredictSettings.with_options`);
the job, the model (:class:`~aerialmtl.inference.model.Predictor`), the runner and the engines read it.
What ``auto`` and the defaults resolve to on this machine and for this checkpoint (device, precision,
engine, threads, MC samples) is a :class:`Resolved`; ``prediction.json`` is written from the two together
(:meth:`PredictSettings.record`).

Where a caller spells the window ``tile`` (the name before ``window``), :meth:`PredictSettings.with_options`
takes it, with a :class:`FutureWarning`; ``prediction.json`` files that say ``tile`` are still read
(:class:`~aerialmtl.formats.prediction.PredictionInfo`).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypedDict

import torch
from typing_extensions import Unpack

from aerialmtl import runtime
from aerialmtl.errors import InputError
from aerialmtl.inference.sun_choice import parse_sun
from aerialmtl.inference.windows import check_tiling
from aerialmtl.sun.solar_position import parse_time

BatchSize = int | Literal["auto"]


@dataclass(frozen=True)
class PredictSettings:
    """How ``predict`` computes the maps of every input (see the module docstring).

    Attributes:
        mc: MC-dropout samples T (1 = single deterministic pass, no uncertainty layers); ``None``: 30
            (:data:`~aerialmtl.inference.model.DEFAULT_MC_SAMPLES`) when the model has dropout, else 1.
        window: largest window side in pixels (multiple of 32). 1024 with ``overlap`` 64 computes ≈ 1.14×
            the output pixels (512 → 1.31×).
        overlap: minimum overlap between neighbouring windows in pixels (blended; see
            :mod:`aerialmtl.inference.windows`).
        batch_size: windows per model call, or ``"auto"`` (:func:`~aerialmtl.inference.runner.auto_batch_size`).
        precision: ``"auto"``, ``"bf16"`` or ``"fp32"`` (:func:`aerialmtl.runtime.resolve_precision`: ``auto``
            is bf16 where the hardware computes it natively and the engine gains from it).
        device: ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.
        engine: ``"auto"`` or an engine's name (:data:`aerialmtl.inference.engines.ENGINES`).
        threads: inference threads on a CPU: a number, or ``"auto"``/``None``
            (:func:`aerialmtl.runtime.resolve_threads`).
        aoi: GeoJSON polygons: windows outside are not computed, pixels outside are nodata.
        probabilities: also write ``class_probabilities.tif`` (K float32 bands).
        calibration: apply the checkpoint's calibration when it has one.
        rescale_input: map an orthophoto whose values do not match the training data's onto the training
            range instead of refusing it (:mod:`aerialmtl.inference.sanity`).
        tta: test-time augmentation: each window also flipped and rotated (8 views); 8× the work.
        compile: ``torch.compile`` the model (torch engine; a warning and the plain model where unavailable).
        seed: base seed of the per-window dropout masks (T > 1): the same seed gives the same maps.
        max_decode_pixels: bound on the pixels decoded per model call with MC dropout (bounds memory, not
            results); ``None``: :data:`~aerialmtl.inference.runner.DECODE_PIXELS` of the device.
        reader_threads: background threads reading windows.
        sun: the sun for the shadow features (:mod:`aerialmtl.inference.sun_choice`): ``"auto"`` (the
            acquisition time and place, else the training fit for an orthophoto of the same flight, else off),
            ``"none"`` (off: the maps of a model without them, to the bit), or ``"AZ,EL"`` in degrees (azimuth
            clockwise from true north, elevation above the horizon).
        acquired: the orthophoto's acquisition time (ISO 8601; without a zone read as UTC) for ``sun="auto"``.
        shadow_fusion: fuse the heights measured from shadows into the height map and its spread, inside the
            network's objects (:mod:`aerialmtl.inference.shadows`); the ``shadow`` and ``shadow_height`` layers
            are written whenever the sun is known, fused or not.
        checkpoint_name: the checkpoint's name in ``prediction.json`` (default: its path, or
            ``<in-memory model>``).
        progress: progress bars.
    """

    mc: int | None = None
    window: int = 1024
    overlap: int = 64
    batch_size: BatchSize = 2
    precision: runtime.Precision = "auto"
    device: str = "auto"
    engine: str = "auto"
    threads: int | str | None = None
    aoi: str | Path | None = None
    probabilities: bool = False
    calibration: bool = True
    rescale_input: bool = False
    tta: bool = False
    compile: bool = False
    seed: int = 0
    max_decode_pixels: int | None = None
    reader_threads: int = 2
    sun: str = "auto"
    acquired: str | None = None
    shadow_fusion: bool = False
    checkpoint_name: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        check_tiling(self.window, self.overlap)
        if self.mc is not None and (not isinstance(self.mc, int) or self.mc < 1):
            raise InputError(
                f"‹mc› must be a positive number of MC-dropout samples, got {self.mc!r}; pass e.g. ‹mc=30› (or 1)",
                param="mc")
        if self.batch_size != "auto" and (not isinstance(self.batch_size, int) or self.batch_size < 1):
            raise InputError(f"‹batch_size› must be ≥ 1 or 'auto', got {self.batch_size!r}; pass e.g. ‹batch_size=4›",
                             param="batch_size")
        runtime.resolve_precision(self.precision, torch.device("cpu"))  # a bad value fails here, naming it
        if self.reader_threads < 1:
            raise InputError(f"reader_threads must be ≥ 1 background thread, got {self.reader_threads!r}; pass e.g. 2")
        runtime.resolve_threads(self.threads)  # a bad value fails here, naming ‹threads›
        parse_sun(self.sun)  # a bad --sun or --acquired fails here, naming it
        if self.acquired is not None:
            parse_time(self.acquired)

    def with_options(self, **options: Unpack[PredictOptions]) -> PredictSettings:
        """These settings with ``options`` (the keywords of :class:`PredictOptions`) replaced, validated again.

        ``tile`` (the window's name before ``window``) is taken as ``window``, with a :class:`FutureWarning`.
        """
        if not options:
            return self
        fields: dict[str, Any] = dict(options)
        if "tile" in fields:
            tile = fields.pop("tile")
            warnings.warn("‹tile› is deprecated for predict: pass ‹window› (the side of the prediction window)",
                          FutureWarning, stacklevel=4)
            fields.setdefault("window", tile)
        return dataclasses.replace(self, **fields)

    def record(self, resolved: Resolved, batch_size: int) -> dict[str, Any]:
        """The settings' fields of ``prediction.json``: these settings with what ``auto`` and the defaults
        resolved to (:class:`Resolved`) and the batch size used (``batch_size``, resolved per window size).
        """
        return {
            "mc_samples": resolved.mc,
            "tta": self.tta,
            "seed": self.seed,
            "window": self.window,
            "overlap": self.overlap,
            "batch_size": batch_size,
            "precision": resolved.precision,
            "engine": resolved.engine,
            "threads": resolved.threads.as_dict() if resolved.device.type == "cpu" else None,
            "device": str(resolved.device),
            "compile": self.compile,
            "sun_setting": self.sun,
            "shadow_fusion": self.shadow_fusion,
        }


class PredictOptions(TypedDict, total=False):
    """The keywords of the Python API's one-call forms: the fields of :class:`PredictSettings` (and ``tile``,
    the window's earlier name).
    """

    mc: int | None
    window: int
    tile: int
    overlap: int
    batch_size: BatchSize
    precision: runtime.Precision
    device: str
    engine: str
    threads: int | str | None
    aoi: str | Path | None
    probabilities: bool
    calibration: bool
    rescale_input: bool
    tta: bool
    compile: bool
    seed: int
    max_decode_pixels: int | None
    reader_threads: int
    sun: str
    acquired: str | None
    shadow_fusion: bool
    checkpoint_name: str | None
    progress: bool


def settings_of(settings: PredictSettings | None, options: PredictOptions) -> PredictSettings:
    """``settings`` (default :class:`PredictSettings`) with the keywords ``options`` of a one-call form."""
    return (settings if settings is not None else PredictSettings()).with_options(**options)


@dataclass(frozen=True)
class Resolved:
    """What :class:`PredictSettings`' ``auto`` values and defaults resolved to for one model on this machine.

    Attributes:
        device: where the model runs.
        engine: the engine that runs it (``torch`` if ``auto`` fell back from another, as recorded).
        precision: ``bf16`` or ``fp32``.
        threads: inference threads and streams on a CPU.
        mc: MC-dropout samples T.
    """

    device: torch.device
    engine: str
    precision: runtime.Resolved
    threads: runtime.CpuThreads
    mc: int


__all__ = ["BatchSize", "PredictOptions", "PredictSettings", "Resolved", "settings_of"]
