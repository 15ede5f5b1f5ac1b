"""Predict's settings: one frozen, validated object, built once and carried unchanged to the engines.

:class:`PredictSettings` holds every option of ``aerialmtl predict`` that decides the maps or how they are
computed (as :class:`~aerialmtl.tiling.tile.TileOptions` does for ``tile``); its fields are the one list of
them. The CLI builds it from its options (one per field, found by name: :func:`~aerialmtl.cli.predict.predict`),
the QGIS provider through the CLI, the Python API from its keywords (:meth:`PredictSettings.with_options`: the
field names, checked against the fields at run time). The job, the model
(:class:`~aerialmtl.inference.model.Predictor`), the runner and the engines read it. Run-time things that do not
decide the maps (progress bars, the checkpoint's display name) are arguments of the calls, not settings.

What ``auto`` and the defaults resolve to on this machine and for this checkpoint (device, precision,
engine, threads, MC samples) is a :class:`ResolvedSettings`. ``prediction.json`` records every field, with what
it resolved to (:meth:`PredictSettings.record`), and ``provenance.settings`` the fields that change the maps
(:meth:`PredictSettings.provenance`): both loop over the fields, so a new field is recorded without another edit.

Where a caller spells the window ``tile`` (the name before ``window``), :meth:`PredictSettings.with_options`
takes it, with a :class:`FutureWarning`; ``prediction.json`` files that say ``tile`` are still read
(:class:`~aerialmtl.formats.prediction.PredictionInfo`).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from aerialmtl import runtime
from aerialmtl.errors import InputError
from aerialmtl.inference.sun_choice import SunChoice, parse_sun
from aerialmtl.inference.windows import check_tiling
from aerialmtl.sun.solar_position import parse_time

BatchSize = int | Literal["auto"]
#: The most steps ``sun_tune`` takes (the bound in time: a step decodes one 512 px crop, ~0.4 s on 2 CPU cores;
#: on the sample area the heights got worse after 30–40 steps).
MAX_TUNE_STEPS = 200


def speed_only(default: Any) -> Any:
    """A field that changes speed or memory, not the maps (not in ``provenance.settings``; the module docstring)."""
    return field(default=default, metadata={"maps": False})


def shadow_setting(default: Any) -> Any:
    """A field that changes the maps only when the shadow features run (in ``provenance.settings`` only then)."""
    return field(default=default, metadata={"maps": "shadows"})


@dataclass(frozen=True)
class PredictSettings:
    """How ``predict`` computes the maps of every input (see the module docstring).

    A field's default is the CLI option's default (a test holds them equal). Fields made with
    :func:`speed_only` change speed or memory only; every other field is part of the maps' provenance.

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
        threads: inference threads on a CPU: a number, or ``"auto"`` (``None`` means the same;
            :func:`aerialmtl.runtime.resolve_threads`).
        aoi: GeoJSON polygons: windows outside are not computed, pixels outside are nodata.
        probabilities: also write ``class_probabilities.tif`` (K float32 bands).
        calibration: apply the checkpoint's calibration when it has one.
        rescale_input: map an orthophoto whose values do not match the training data's onto the training
            range instead of refusing it (:mod:`aerialmtl.inference.sanity`; the map applied is recorded as
            ``input_rescale``).
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
            are written whenever the sun is known, fused or not. Refused with ``sun="none"`` (no shadows to
            measure) and for heights without a spread to weigh (:meth:`check_fusion`): an explicit request that
            cannot act is an error, not a run that says it fused.
        sun_tune: Adam steps of the height decoder on the inputs' own cast shadows before predicting
            (:mod:`aerialmtl.inference.self_tune`), 0 to :data:`MAX_TUNE_STEPS`; 0: off. Refused with ``sun="none"``.
    """

    mc: int | None = None
    window: int = speed_only(1024)
    overlap: int = speed_only(64)
    batch_size: BatchSize = speed_only("auto")
    precision: runtime.Precision = "auto"
    device: str = speed_only("auto")
    engine: str = "auto"
    threads: int | str | None = speed_only("auto")
    aoi: str | Path | None = None
    probabilities: bool = False
    calibration: bool = True
    rescale_input: bool = speed_only(False)
    tta: bool = False
    compile: bool = speed_only(False)
    seed: int = 0
    max_decode_pixels: int | None = speed_only(None)
    reader_threads: int = speed_only(2)
    sun: str = shadow_setting("auto")
    acquired: str | None = shadow_setting(None)
    shadow_fusion: bool = shadow_setting(False)
    sun_tune: int = shadow_setting(0)

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
        sun = parse_sun(self.sun)  # a bad --sun or --acquired fails here, naming it
        if self.acquired is not None:
            parse_time(self.acquired)
        if (not isinstance(self.sun_tune, int) or isinstance(self.sun_tune, bool)
                or not 0 <= self.sun_tune <= MAX_TUNE_STEPS):
            raise InputError(f"‹sun_tune› is a number of steps from 0 to {MAX_TUNE_STEPS}, got {self.sun_tune!r}; "
                             "pass e.g. ‹sun_tune=30› (0: off)", param="sun_tune")
        if self.sun_tune and sun == "none":
            raise InputError("‹sun_tune› tunes the heights on the orthophotos' cast shadows, and ‹sun=none› turns the "
                             "shadows off: drop ‹sun_tune›, or pass ‹sun› auto or AZ,EL")
        if self.shadow_fusion and sun == "none":
            raise InputError("‹shadow_fusion› moves heights towards those their shadows measure, and ‹sun=none› turns "
                             "the shadows off: drop ‹shadow_fusion›, or pass ‹sun› auto or AZ,EL")

    def check_tune(self, tasks: tuple[str, ...], checkpoint: str) -> None:
        """Refuse ``sun_tune`` for a model of ``tasks`` without ``height`` (nothing to tune); ``checkpoint`` names it.

        Raises:
            InputError: naming ‹sun_tune›, why, and the fix.
        """
        if self.sun_tune and "height" not in tasks:
            raise InputError(f"‹sun_tune› tunes the heights, and {checkpoint} predicts none (tasks: "
                             f"{', '.join(tasks)}): drop ‹sun_tune›")

    def check_fusion(self, mc: int, tasks: tuple[str, ...], aleatoric: bool, checkpoint: str) -> None:
        """Refuse ``shadow_fusion`` for a model whose heights it cannot move.

        Fusion weighs each height by its spread: a model of ``tasks`` without ``height`` has none to move, and at
        ``mc`` = 1 MC sample (the resolved T) without ``tta`` the heights of a model without an ``aleatoric``
        head have no spread (a run would change nothing and say it fused). ``checkpoint`` names the model.

        Raises:
            InputError: naming ‹shadow_fusion›, why, and the fix.
        """
        if not self.shadow_fusion:
            return
        if "height" not in tasks:
            raise InputError(f"‹shadow_fusion› fuses heights, and {checkpoint} predicts none (tasks: "
                             f"{', '.join(tasks)}): drop ‹shadow_fusion›")
        if mc > 1 or self.tta or aleatoric:
            return
        if self.mc is not None:
            raise InputError(f"‹shadow_fusion› weighs each height by its spread, and with ‹mc=1› the heights of "
                             f"{checkpoint} (no aleatoric head) have none: pass ‹mc› 30 (or ‹tta›), or drop "
                             "‹shadow_fusion›")
        raise InputError(f"‹shadow_fusion› weighs each height by its spread, and {checkpoint} has neither dropout nor "
                         "an aleatoric head: its heights have none (T = 1); pass ‹tta›, or drop ‹shadow_fusion›")

    def with_options(self, **options: Any) -> PredictSettings:
        """These settings with ``options`` (keywords named like the fields) replaced, validated again.

        ``tile`` (the window's name before ``window``) is taken as ``window``, with a :class:`FutureWarning`.

        Raises:
            InputError: a keyword that names no field (the message lists the fields).
        """
        if not options:
            return self
        if "tile" in options:
            tile = options.pop("tile")
            warnings.warn("‹tile› is deprecated for predict: pass ‹window› (the side of the prediction window)",
                          FutureWarning, stacklevel=4)
            options.setdefault("window", tile)
        names = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(options) - set(names))
        if unknown:
            raise InputError(f"predict has no setting {', '.join(f'‹{u}›' for u in unknown)}; the settings are "
                             f"{', '.join(names)}", param=unknown[0])
        return dataclasses.replace(self, **options)

    def _values(self, resolved: ResolvedSettings) -> dict[str, Any]:
        """Every field's value as JSON, with what ``auto`` or a default resolved to in its place.

        The fields of ``resolved`` are named like the settings they resolve.
        """
        values: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(resolved, f.name) if hasattr(resolved, f.name) else getattr(self, f.name)
            values[f.name] = _json(value, resolved)
        return values

    def record(self, resolved: ResolvedSettings, batch_size: int) -> dict[str, Any]:
        """``prediction.json``'s ``settings``: every field, resolved.

        ``resolved``: what ``auto`` and the defaults resolved to; ``batch_size``: the batch size used (resolved per
        window size).
        """
        return {**self._values(resolved), "batch_size": batch_size}

    def provenance(self, resolved: ResolvedSettings, shadows: bool = False, **recorded: Any) -> dict[str, Any]:
        """``provenance.settings`` of ``prediction.json``: the fields that change the maps, resolved.

        All fields but the :func:`speed_only` ones (and the :func:`shadow_setting` ones unless the shadow features
        ran: ``shadows``), ``mc`` under its recorded name ``mc_samples``; ``recorded`` replaces or adds values the
        model knows better (the AOI's fingerprint, whether calibration was applied, ...).
        """
        values = self._values(resolved)
        maps = {True, "shadows"} if shadows else {True}
        kept = {f.name: values[f.name] for f in dataclasses.fields(self) if f.metadata.get("maps", True) in maps}
        kept["mc_samples"] = kept.pop("mc")
        if not kept.get("sun_tune"):  # off: the provenance of the runs before the setting existed, unchanged
            kept.pop("sun_tune", None)
        return {**kept, **recorded}


def _json(value: Any, resolved: ResolvedSettings) -> Any:
    """``value`` as ``prediction.json`` holds it (a device and a path as text, threads as a mapping on a CPU)."""
    if isinstance(value, runtime.CpuThreads):
        return value.as_dict() if resolved.device.type == "cpu" else None
    if isinstance(value, (torch.device, Path)):
        return str(value)
    return value


def fusion_record(asked: bool, shadows: bool, choice: SunChoice | None) -> dict[str, Any]:
    """``prediction.json``'s ``fusion`` of one input: ``{"applied": bool, "reason": str}``.

    ``asked``: ``shadow_fusion``; ``shadows``: the run had the shadow step; ``choice``: the input's sun (``None``
    when the step was off). Applied means every object of the input whose shadow was measured (its
    ``shadow_height``) had its height moved.
    """
    if not asked:
        return {"applied": False, "reason": "not asked (shadow_fusion off)"}
    if not shadows:
        return {"applied": False, "reason": "no shadow layers in this run (the checkpoint holds no shadow classifier)"}
    if choice is None or not choice.on:
        note = choice.note if choice is not None else "no sun"
        return {"applied": False, "reason": f"no sun for this orthophoto: {note}"}
    return {"applied": True, "reason": "the heights of the objects whose shadows were measured (shadow_height) "
                                       "moved towards them, weighted by both spreads"}


def settings_of(settings: PredictSettings | None, options: dict[str, Any]) -> PredictSettings:
    """``settings`` (default :class:`PredictSettings`) with the keywords ``options`` of a one-call form."""
    return (settings if settings is not None else PredictSettings()).with_options(**options)


@dataclass(frozen=True)
class ResolvedSettings:
    """What the ``auto`` values and defaults of :class:`PredictSettings` resolved to for one model on this machine.

    Each field is named like the setting it resolves.

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


__all__ = ["BatchSize", "PredictSettings", "ResolvedSettings", "fusion_record", "settings_of", "shadow_setting",
           "speed_only"]
