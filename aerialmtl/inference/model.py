"""Streaming prediction of orthophotos: the model, loaded once, that computes strips of window rows.

A :class:`Predictor` is a model loaded once with its settings (:class:`~aerialmtl.inference.settings.PredictSettings`
and what they resolved to), its output schema (:attr:`Predictor.layers`) and its fingerprint: it computes any
number of orthophotos. What runs once per input — claiming the prediction folder, the writer's staging files,
the commit and ``prediction.json`` — is the job's (:class:`~aerialmtl.inference.job.InputJob`); the whole
raster is the one-strip case, and a ``torchrun`` rank computes one strip of the window rows of an input it
shares (:mod:`aerialmtl.inference.jobs`). The orthophoto's header is read once into an
:class:`~aerialmtl.inference.ortho.OrthoInput` (grid, bands, window plan, value check) that travels
through the job.

A strip (:mod:`~aerialmtl.inference.strips`) is read → model → stitch → write, each stage overlapping the
others:

1. :class:`~aerialmtl.inference.reader.WindowReader` reads and decodes the windows of the plan
   (:func:`~aerialmtl.inference.windows.plan_windows`) on the prediction grid at the model's GSD in
   background threads, a few windows ahead;
2. :class:`~aerialmtl.inference.runner.ModelRunner` normalises them on the device and runs the model in
   batches of windows of one window row (plain forward for T = 1, MC dropout for T > 1);
3. :class:`~aerialmtl.inference.stitch.Stitcher` blends the window statistics on the device (in a thread of
   its own while the model computes the next batches, on a GPU or a host of 4 cores or more) and hands back
   finished blocks in their output dtypes, following one output schema
   (:func:`~aerialmtl.formats.prediction.prediction_layers`);
4. the job's :class:`~aerialmtl.inference.writer.PredictionWriter` writes the blocks into staging files
   in a background thread; at the commit it converts every layer to a COG (the layers in parallel, each
   on several threads) and renames everything into place at once.

Device, precision, autocast, the compile fallback and the GDAL settings come from
:mod:`aerialmtl.runtime`, as for training.
The engine is chosen once per predictor (:meth:`Predictor.fit_engine`: for the job, once the jobs have read
its inputs' headers; else at first use) and runs in one runner, built then.

Memory holds a few windows (reader queue, accumulators, blocks in flight) plus the rows two window rows
share (a few KiB per raster column): it does not grow with the raster height, and barely with its
width. Windows with no valid input pixel (nodata, outside the AOI) are not computed.

:func:`~aerialmtl.inference.jobs.predict_raster` is the one-call form and
:func:`~aerialmtl.inference.jobs.predict_many` its many-input form (in one process or many, torchrun); this
module imports neither the job nor the jobs (an import-linter contract, pyproject.toml).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import torch

from aerialmtl import runtime
from aerialmtl.formats import checkpoint as checkpoint_format  # read_model at call time: tests patch it
from aerialmtl.formats.checkpoint import ModelMeta, model_fingerprint
from aerialmtl.formats.prediction import PROVENANCE_KEY, RECORD_KEYS, LayerSpec, prediction_layers
from aerialmtl.formats.stac import model_summary
from aerialmtl.inference import stitch_kernel
from aerialmtl.inference.engine_choice import EngineChoice, Job, choose_engine
from aerialmtl.inference.engines import ENGINES, EngineSetup, engine_spec
from aerialmtl.inference.model_record import CheckpointModel, any_record, make_record, read_record, write_record
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.runner import ModelRunner, auto_batch_size
from aerialmtl.inference.sanity import check_calibration
from aerialmtl.inference.settings import PredictSettings, ResolvedSettings, fusion_record, settings_of
from aerialmtl.inference.stitch import Block
from aerialmtl.inference.strips import StripResult, compute_strip
from aerialmtl.inference.sun_choice import SunChoice, choose_sun
from aerialmtl.inference.windows import Plan
from aerialmtl.io.fingerprint import file_fingerprint, input_fingerprint
from aerialmtl.models import class_kernel

if TYPE_CHECKING:
    from aerialmtl.inference.self_tune import TuneReport
    from aerialmtl.inference.shadows import ShadowStep

log = logging.getLogger(__name__)

#: MC-dropout samples when the caller does not say otherwise and the model has dropout.
DEFAULT_MC_SAMPLES = 30


def _record_root(engine: str, device: torch.device) -> Path | None:
    """Where the checkpoint records of a run with the ``engine`` option on ``device`` are kept: the folder of the
    first engine it may run on that keeps them (:attr:`~aerialmtl.inference.engines.base.EngineSpec.record_root`),
    ``None`` where none does.
    """
    if device.type != "cpu":
        return None
    for name, spec in ENGINES.items():
        if engine in ("auto", name) and spec.record_root is not None:
            return spec.record_root()
    return None


def _load(checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta], root: Path | None = None
          ) -> tuple[torch.nn.Module | CheckpointModel, ModelMeta, str, str | None]:
    """``(model, meta, name, fingerprint)`` of ``checkpoint``.

    The fingerprint is that of the checkpoint bytes loaded (``None`` for a model given in memory: computed from its
    weights when needed).

    With ``root`` (the checkpoint records of an engine the run may use: :func:`_record_root`), a checkpoint file
    whose record is there (:mod:`aerialmtl.inference.model_record`) is not loaded: its bytes are hashed, and the
    model is a :class:`~aerialmtl.inference.model_record.CheckpointModel` that loads them only if something needs
    the weights. Where ``root`` holds no record at all (a cold cache), the bytes are not hashed twice. A checkpoint
    loaded here gets its record when that engine is built (:meth:`Predictor.runner`), not before: a run that the
    choice gives to another engine does not pay for it.
    """
    if isinstance(checkpoint, tuple):
        model, meta = checkpoint
        return model, meta, "<in-memory model>", None
    if root is not None and any_record(root):
        try:
            digest: str | None = checkpoint_format.file_sha256(checkpoint)
        except OSError:  # read_model says what is wrong with the file
            digest = None
        record = read_record(digest, root) if digest is not None else None
        if digest is not None and record is not None:
            return CheckpointModel(checkpoint, digest, record), record.meta, str(checkpoint), digest
    model, meta, loaded = checkpoint_format.read_model(checkpoint)
    return model, meta, str(checkpoint), loaded


# ---- the predictor -----------------------------------------------------------------------------
class Predictor:
    """A model ready to predict orthophotos: read → model → stitch (the job writes).

    Args:
        checkpoint: checkpoint path, or ``(model, meta)`` already loaded.
        settings: predict's settings (:class:`~aerialmtl.inference.settings.PredictSettings`; default: its
            defaults).
        checkpoint_name: the checkpoint's name in ``prediction.json`` and in messages (default: its path, or
            ``<in-memory model>``).
        options: the Python API's keywords, one per field of the settings (named like them), applied over
            ``settings`` (:meth:`~aerialmtl.inference.settings.PredictSettings.with_options`).

    What ``auto`` and the defaults resolve to is :attr:`resolved` (and, one by one, :attr:`device`,
    :attr:`engine`, :attr:`precision`, :attr:`threads`, :attr:`mc`).
    """

    def __init__(self, checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta],
                 settings: PredictSettings | None = None, *, checkpoint_name: str | None = None,
                 **options: Any) -> None:
        self.settings = s = settings_of(settings, options)
        self.device = runtime.resolve_device(s.device)
        #: Inference threads and streams (:func:`aerialmtl.runtime.resolve_threads`).
        self.threads = runtime.resolve_threads(s.threads)
        if self.threads.source != "auto" and self.device.type == "cpu":
            torch.set_num_threads(self.threads.threads)
        model, self.meta, name, loaded_fingerprint = _load(checkpoint, _record_root(s.engine, self.device))
        self.checkpoint_name = checkpoint_name or name
        self._checkpoint = checkpoint
        self._model = model  # as loaded (or its record): the one runner's engine is built from it
        self._fingerprint: str | None = loaded_fingerprint  # of the bytes loaded, not of the path at commit
        self.mc = s.mc if s.mc is not None else (DEFAULT_MC_SAMPLES if self.meta.model.dropout > 0 else 1)
        if s.calibration:
            check_calibration(self.meta, self.checkpoint_name)
        self.calibration = self.meta.calibration if s.calibration else None
        self.calibration_available = self.meta.calibration is not None
        self._choice: EngineChoice | None = None
        self._runner: ModelRunner | None = None
        if s.engine != "auto":  # a named engine does not depend on the job: checked (and refused) here
            self.fit_engine(())
        tasks = tuple(self.meta.model.tasks)
        self.num_classes = self.meta.classes.num_classes if self.meta.classes is not None and "classes" in tasks else 0
        #: The shadow features (:mod:`aerialmtl.inference.shadows`), ``None`` when off for the whole run.
        self.shadows = self._shadow_step()
        self._suns: dict[str, SunChoice] = {}
        #: What :meth:`tune` did (``--sun-tune``), ``None`` before it or where it tuned nothing.
        self.tuned: TuneReport | None = None
        #: The output schema: one :class:`LayerSpec` per layer, in file order.
        self.layers: tuple[LayerSpec, ...] = prediction_layers(tasks, self.meta.classes, self.mc, s.probabilities,
                                                                 aleatoric=self.meta.model.aleatoric, tta=s.tta,
                                                                 unfamiliarity=self.meta.familiarity is not None,
                                                                 shadows=self.shadows is not None)
        if self.meta.familiarity is None:  # said once per run (and in prediction.json's model summary)
            log.info("%s holds no feature density: no unfamiliarity layer (a model trained with this version "
                     "fits one after training)", self.checkpoint_name)
        self._batch: dict[tuple[int, int], int] = {}
        if self.device.type == "cpu":  # the kernels loaded before any output exists (class_kernel.prepare)
            if self.mc > 1:
                class_kernel.prepare()
            if "classes" in self.meta.model.tasks:
                stitch_kernel.prepare()

    @property
    def aoi(self) -> str | Path | None:
        """The AOI of the settings (windows outside it are not computed)."""
        return self.settings.aoi

    def _shadow_step(self) -> ShadowStep | None:
        """The shadow features of this run, or ``None`` when they are off.

        On unless ``--sun none``, for a height model whose checkpoint holds the training area's shadow classifier
        (``meta.sun``; fitted by ``train`` since this version).
        """
        s, sun = self.settings, self.meta.sun
        s.check_fusion(self.mc, tuple(self.meta.model.tasks), self.meta.model.aleatoric, self.checkpoint_name)
        s.check_tune(tuple(self.meta.model.tasks), self.checkpoint_name)
        if s.sun == "none" or "height" not in self.meta.model.tasks:
            return None
        if sun is None or sun.shadow_model is None:
            why = ("holds no sun fit (trained before this version: `aerialmtl train` fits one)" if sun is None else
                   f"has no shadow classifier: {sun.reason}")
            if s.sun != "auto" or s.shadow_fusion:
                warnings.warn(f"--sun {s.sun}: {self.checkpoint_name} {why}; no shadow layers", UserWarning,
                              stacklevel=3)
            return None
        from aerialmtl.inference.shadows import ShadowStep  # scipy and the sun's kernels: only a run that casts shadows
        from aerialmtl.sun.colour import ShadowModel

        return ShadowStep(ShadowModel.from_dict(sun.shadow_model), self.meta.gsd, s.shadow_fusion,
                          workers=self.threads.threads)

    def sun_for(self, src: OrthoInput) -> SunChoice | None:
        """The sun of ``src``, or ``None`` when the shadow features are off for the run.

        Chosen by :func:`~aerialmtl.inference.sun_choice.choose_sun`, once per input, and said once.
        """
        if self.shadows is None:
            return None
        key = str(src.path)
        if key not in self._suns:
            choice = choose_sun(self.settings.sun, self.settings.acquired, src.path, src.grid, src.tags,
                                self.meta.sun)
            self._suns[key] = choice
            if choice.on:
                log.info("%s: %s", src.name, choice.note)
            else:
                warnings.warn(f"{src.name}: no shadow features: {choice.note}", UserWarning, stacklevel=2)
        return self._suns[key]

    def sun_off(self, src: OrthoInput, note: str) -> None:
        """Switch the shadow layers off for ``src`` after :meth:`sun_for` chose its sun: its own shadows disagree
        (:meth:`aerialmtl.inference.shadows.ShadowStep.check_sun`). Said once; ``prediction.json`` records it.
        """
        key = str(src.path)
        before = self._suns.get(key)
        if before is not None and not before.on:
            return
        self._suns[key] = SunChoice(None, None, None, "checked on the orthophoto", note)
        warnings.warn(f"{src.name}: no shadow features: {note}", UserWarning, stacklevel=2)

    def tune(self, srcs: Sequence[OrthoInput]) -> TuneReport | None:
        """With ``sun_tune`` steps, tune the height decoder on ``srcs``' own cast shadows before anything is
        predicted (:mod:`aerialmtl.inference.self_tune`); the run then predicts with the tuned weights, whose
        fingerprint is the checkpoint's in ``prediction.json`` (no engine record or cache of the file is used).

        Returns the report (also :attr:`tuned`), or ``None`` where nothing was tuned: the setting is 0, no input
        has a sun (said once), or none has a crop with enough pixels to compare (said once).
        """
        steps = self.settings.sun_tune
        if not steps or self.tuned is not None:
            return self.tuned
        if self._runner is not None:
            raise RuntimeError("Predictor.tune: the engine is built already; tune before predicting")
        from aerialmtl.sun.position import Sun

        inputs = [(src, Sun(choice.grid_azimuth_deg % 360.0, choice.elevation_deg)) for src in srcs
                  if (choice := self.sun_for(src)) is not None and choice.on
                  and choice.grid_azimuth_deg is not None and choice.elevation_deg is not None]
        if self.shadows is None or not inputs:
            sun = self.meta.sun
            why = ("no input has a sun (each input's warning says why)" if self.shadows is not None else
                   f"{self.checkpoint_name} holds no sun fit (trained before this version: `aerialmtl train` fits one)"
                   if sun is None else f"{self.checkpoint_name} has no shadow classifier: {sun.reason}")
            warnings.warn(f"--sun-tune {steps}: {why}; the heights are not tuned", UserWarning, stacklevel=2)
            return None
        from aerialmtl.inference.self_tune import read_crops, tune_height_branch

        crops = read_crops(inputs, self.meta, self.shadows.model, self.settings.aoi, self.threads.threads)
        if not crops:
            warnings.warn(f"--sun-tune {steps}: no part of the inputs has enough pixels whose shadows can be "
                          "compared (each crop needs a quarter of its pixels valid, in the AOI, with the sun's ray "
                          "inside it); the heights are not tuned", UserWarning, stacklevel=2)
            return None
        model = self._model.get() if isinstance(self._model, CheckpointModel) else self._model
        self.tuned = tune_height_branch(model, self.meta, crops, steps, self.calibration)
        self._model, self._checkpoint, self._fingerprint = model, (model, self.meta), None
        log.info("tuned the heights on the orthophotos' shadows: %d steps on %d crops, shadow match %.4f → %.4f "
                 "(%.1f s)", steps, len(crops), self.tuned.ll_before, self.tuned.ll_after, self.tuned.seconds)
        return self.tuned

    @property
    def model(self) -> torch.nn.Module:
        """The prepared model the runner predicts with."""
        return self.runner.model

    # ---- inputs -----------------------------------------------------------------------------------
    def open(self, ortho: str | Path | OrthoInput, warn: bool = True) -> OrthoInput:
        """Read the header of ``ortho`` and a sample of its values once.

        :meth:`OrthoInput.open <aerialmtl.inference.ortho.OrthoInput.open>` reads them; an :class:`OrthoInput` is
        returned as it is.

        Args:
            ortho: the orthophoto.
            warn: warn when it is resampled to the model's GSD or has bands the model does not read.

        Raises:
            AlignmentError / InputError: unusable georeferencing or bands, or values unlike the training
                data's (:func:`~aerialmtl.inference.sanity.check_input_values`; messages name the fix).
        """
        if isinstance(ortho, OrthoInput):
            return ortho
        src = OrthoInput.open(ortho, self.meta, self.settings.window, self.settings.overlap,
                               rescale_input=self.settings.rescale_input)
        if warn:
            src.warn_resampled(self.meta, stacklevel=4)
            src.warn_unused_bands(self.meta, stacklevel=4)
        return src

    def resolved_batch_size(self, plan: Plan) -> int:
        """Windows per model call for windows of ``plan`` (resolves ``"auto"`` once per window size)."""
        if self.settings.batch_size != "auto":
            return int(self.settings.batch_size)
        key = (plan.rows.size, plan.cols.size)
        if key not in self._batch:
            self._batch[key] = auto_batch_size(lambda: self.runner.net, self.meta.model.in_channels, *key,
                                               self.device, self.precision)
        return self._batch[key]

    # ---- the engine -------------------------------------------------------------------------------
    def fit_engine(self, srcs: Sequence[OrthoInput]) -> EngineChoice:
        """Choose the engine, once, for the job of predicting ``srcs`` (none: a job not known).

        :func:`~aerialmtl.inference.engine_choice.choose_engine` weighs, under ``engine: auto``, each engine's
        speed and a cold cache's compilation against the job's size (:class:`~aerialmtl.inference.engine_choice.Job`).
        The jobs (:mod:`aerialmtl.inference.jobs`) call it once the inputs' headers are read; otherwise the first
        use of :attr:`choice` or :attr:`runner` does, without a job. Later calls return the first choice.
        """
        if self._choice is not None:
            return self._choice
        s = self.settings
        shapes = {(src.plan.rows.size, src.plan.cols.size) for src in srcs}
        job = None
        if srcs:
            work = sum(src.plan.num_windows * src.plan.rows.size * src.plan.cols.size for src in srcs) / 1e6
            job = Job(self.device.type, work, self.mc * (8 if s.tta else 1))
        self._choice = choose_engine(s.engine, s.precision, self.device, self._model, job=job,
                                     cached=lambda name, precision: self._cached(name, precision, shapes))
        if s.compile and not engine_spec(self._choice.engine).takes_compile:
            label = engine_spec(self._choice.engine).label
            warnings.warn(f"‹compile› applies to the torch engine; the {label} engine compiles the model itself",
                          UserWarning, stacklevel=3)
        return self._choice

    def _setup(self, engine: str, precision: Literal["fp32", "bf16"]) -> EngineSetup:
        """What engine ``engine`` at ``precision`` is built from (its cache keyed by the checkpoint's hash where
        it keeps checkpoint records: hashed once, for the provenance too).
        """
        resolved = ResolvedSettings(self.device, engine, precision, self.threads, self.mc)
        keyed = engine_spec(engine).record_root is not None
        return EngineSetup(self._model, self.meta, self.settings, resolved, self.fingerprint if keyed else None)

    def _cached(self, engine: str, precision: Literal["fp32", "bf16"], shapes: set[tuple[int, int]]) -> bool:
        """Whether engine ``engine``'s cache holds the graphs of windows of ``shapes`` (the choice asks)."""
        probe = engine_spec(engine).cached
        return probe is not None and probe(self._setup(engine, precision), shapes, self.mc)

    @property
    def choice(self) -> EngineChoice:
        """Engine and precision, and why (``auto``: :mod:`~aerialmtl.inference.engine_choice`)."""
        return self.fit_engine(())

    @property
    def engine(self) -> str:
        """The engine that runs the model (a name of :data:`~aerialmtl.inference.engines.ENGINES`)."""
        return self.choice.engine

    @property
    def precision(self) -> Literal["fp32", "bf16"]:
        """The precision the model runs at."""
        return self.choice.precision

    @property
    def resolved(self) -> ResolvedSettings:
        """What the settings resolved to."""
        return ResolvedSettings(self.device, self.engine, self.precision, self.threads, self.mc)

    @property
    def runner(self) -> ModelRunner:
        """The model runner on the chosen engine, built once (:class:`~aerialmtl.inference.runner.ModelRunner`)."""
        if self._runner is None:
            setup = self._setup(self.engine, self.precision)
            self._keep_record(self.engine)
            self._runner = ModelRunner(setup.model, self.meta, self.settings, setup.resolved, setup.weights_key)
        return self._runner

    def _keep_record(self, engine: str) -> None:
        """Write the record of a checkpoint file this run loaded, for the next run, where ``engine`` keeps records
        (:mod:`aerialmtl.inference.model_record`: its warm path then never builds the torch model).
        """
        spec = engine_spec(engine)
        if (spec.record_root is None or self.device.type != "cpu" or isinstance(self._checkpoint, tuple)
                or not isinstance(self._model, torch.nn.Module) or self._fingerprint is None):
            return
        root = spec.record_root()
        made = make_record(self._model, self.meta) if root is not None else None
        if root is not None and made is not None:
            write_record(self._fingerprint, made, root)

    # ---- computing --------------------------------------------------------------------------------
    def compute(self, src: OrthoInput, rows: tuple[int, int], write: Callable[[Block], None], *,
                progress: bool = True) -> StripResult:
        """Read, run and stitch window rows ``rows = [start, stop)`` of ``src``'s plan
        (:func:`~aerialmtl.inference.strips.compute_strip`); each finished block goes to ``write``.
        """
        return compute_strip(self, src, rows, write, progress)

    # ---- run information --------------------------------------------------------------------------
    @property
    def fingerprint(self) -> str:
        """The model's fingerprint (SHA-256).

        Of the checkpoint bytes that were loaded (:func:`~aerialmtl.formats.checkpoint.read_checkpoint`), or of the
        weights of a model given in memory.
        """
        if self._fingerprint is None:
            assert isinstance(self._checkpoint, tuple)
            self._fingerprint = model_fingerprint(*self._checkpoint)
        return self._fingerprint

    def provenance(self, src: OrthoInput) -> dict[str, Any]:
        """What makes the maps of ``src`` (``provenance`` in prediction.json, :mod:`aerialmtl.formats.prediction`)."""
        s = self.settings
        settings = s.provenance(self._ran_as(), shadows=self.shadows is not None, aoi=file_fingerprint(s.aoi),
                                calibration=self.calibration is not None,
                                input_rescale=None if src.rescale is None else list(src.rescale))
        return {
            "checkpoint": self.fingerprint,
            "settings": settings,
            "input": src.fingerprint if src.fingerprint is not None else input_fingerprint(src.path),
        }

    def record_settings(self, src: OrthoInput) -> dict[str, Any]:
        """The model's and the settings' fields of ``src``'s ``prediction.json``.

        See :class:`~aerialmtl.formats.prediction.PredictionRecord` (the job adds the input's and the run's): the
        settings with what they resolved to (:meth:`PredictSettings.record
        <aerialmtl.inference.settings.PredictSettings.record>`).
        """
        settings = self.settings.record(self._ran_as(), self.resolved_batch_size(src.plan))
        return {
            "checkpoint": self.checkpoint_name,
            "model": model_summary(self.meta),
            **{k: v for k, v in settings.items() if k in RECORD_KEYS},
            "mc_samples": settings["mc"],
            "sun_setting": settings["sun"],
            "settings": settings,
            "engine_choice": self.choice.as_dict(),
            "calibration": self.calibration_info(),
            **({"sun": choice.record()} if (choice := self.sun_for(src)) is not None else {}),
            "fusion": fusion_record(self.settings.shadow_fusion, self.shadows is not None, self.sun_for(src)),
            **({"sun_tune": self.tuned.record()} if self.tuned is not None else {}),
            PROVENANCE_KEY: self.provenance(src),
        }

    def _ran_as(self) -> ResolvedSettings:
        """What the settings resolved to, with the engine that ran (``torch`` if ``auto`` fell back)."""
        return dataclasses.replace(self.resolved, engine=self.runner.engine.name)

    def calibration_info(self) -> dict[str, Any]:
        """``prediction.json``'s ``calibration``: whether the checkpoint's calibration was applied, and which."""
        cal = self.meta.calibration
        if cal is None:
            return {"applied": False, "reason": "the checkpoint has no calibration"}
        on = self.calibration is not None
        info: dict[str, Any] = {"applied": on and (cal.height_applied or cal.spread_applied),
                                "height_map_applied": on and cal.height_applied,
                                "spread_map_applied": on and cal.spread_applied,
                                "method": cal.method, "n_pixels": cal.n_pixels, "source": cal.source,
                                "summary": cal.summary()}
        if cal.height_applied:
            info["height_knots_m"] = [list(cal.height_x), list(cal.height_y)]
        if cal.spread_applied:
            info.update({"std_scale": cal.std_scale, "std_floor_m": cal.std_floor} if not cal.std_edges else
                        {"std_range_edges_m": list(cal.std_edges), "std_scales": list(cal.std_scales),
                         "std_floors_m": list(cal.std_floors)})
        if on and not (cal.height_applied or cal.spread_applied):
            info["reason"] = f"validation kept neither part: {cal.notes}"
        if self.calibration is None:
            info["reason"] = "switched off (--no-calibration)"
        return info


__all__ = ["DEFAULT_MC_SAMPLES", "Predictor", "StripResult"]
