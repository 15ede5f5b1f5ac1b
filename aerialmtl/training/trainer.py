"""The trainer behind ``aerialmtl train``: data → D3-Net → masked losses → task weighting → Adam.

:class:`Trainer` is built from small parts, each readable and testable alone:

* data — :meth:`Trainer.build_data`: the decoded patch cache (:mod:`aerialmtl.data.cache`), the run's batch
  order (:class:`~aerialmtl.data.batches.EpochOrder`) and the loaders; batches are augmented on the
  training device (:func:`~aerialmtl.data.batches.prepare_batch`), on a CPU by one thread in one compiled pass
  (:class:`~aerialmtl.data.prefetch.AssembledBatches`);
* model and optimizer — :meth:`Trainer.build_model`, :func:`build_optimizer`;
* the step — :class:`StepModule` (forward, losses, weighting; what DistributedDataParallel wraps) and the
  shared loop's :meth:`~aerialmtl.training.steploop.StepLoop.train_step` (the same step ``pretrain`` runs);
* validation — :meth:`Trainer.validate` (all processes, sums reduced);
* checkpoints and resume — :meth:`Trainer.checkpoint` (the shared :meth:`~aerialmtl.training.steploop.StepLoop.save`),
  :mod:`aerialmtl.training.resume`, :mod:`aerialmtl.training.state`;
  fine-tuning from a checkpoint — :mod:`aerialmtl.training.finetune`;
* logging — :class:`~aerialmtl.training.runlog.CsvLog` and :class:`~aerialmtl.training.steploop.LossWindow`.

Several processes (``torchrun``) are handled by :mod:`aerialmtl.training.distributed`; here they appear
only as ``self.ctx`` (rank, world size, collectives that are no-ops for one process).

Device, precision, autocast and the compile fallback come from :mod:`aerialmtl.runtime` (as for prediction).
``precision: auto`` is bf16 autocast on a CUDA GPU with bf16 and fp32 otherwise (CPUs without bf16 units run
it hundreds of times slower; on CPUs with them see :data:`CPU_BF16_TRAINING`). Losses are computed in float32
either way. The model runs in ``channels_last``; ``compile: true`` (``--compile``) wraps it in
``torch.compile`` and falls back to eager execution with a warning if compilation fails.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from aerialmtl import runtime
from aerialmtl.config import to_dict
from aerialmtl.data.batches import EpochOrder, prepare_batch
from aerialmtl.errors import InputError, NonFiniteError
from aerialmtl.formats.checkpoint import (
    SURFACE_HEIGHTS_M,
    ModelMeta,
    height_slack,
    same_weights,
    update_meta,
)
from aerialmtl.formats.run import LOG_COLUMNS, RUN_FILES, CsvLog, RunFolder
from aerialmtl.io.oserrors import writing
from aerialmtl.models.calibration import Calibration
from aerialmtl.models.familiarity import FeatureDensity
from aerialmtl.progress import announce
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.tiling.height_support import (
    TallCount,
    cache_tall_count,
    cannot_judge,
    validation_heights_warning,
)
from aerialmtl.training.calibrate import calibrate_checkpoint
from aerialmtl.training.familiarity import familiarize_checkpoint
from aerialmtl.training.metrics import ConfusionMeter, HeightMeter
from aerialmtl.training.objective import validation_score
from aerialmtl.training.setup import Batches, TrainSetup
from aerialmtl.training.steploop import LOSS_GROWTH, LossWindow, StepLoop
from aerialmtl.training.sun import fit_training_sun, store_sun
from aerialmtl.training.sun_beside import SunBeside, beside_steps

log = logging.getLogger(__name__)

#: A validation class loss above this many times ln K (an untrained model's) means the run diverged.
EXPLODED_CLASS_LOSS = 20.0


@dataclass
class TrainResult:
    """What a call to :func:`~aerialmtl.training.loop.train` produced.

    Attributes:
        run_dir: the run folder.
        last_checkpoint, best_checkpoint, log_path, config_path: files in ``run_dir``.
        step: optimisation steps done in total (including resumed ones).
        epoch: completed epochs.
        stopped_by: ``"epochs"``, ``"max_steps"``, ``"max_time"`` or ``"patience"`` (early stopping).
        elapsed_s: wall-clock seconds of this call.
        metrics: the last validation (``val_loss_<task>``, ``height_mae``/``height_rmse`` in metres,
            ``oa``/``miou``, ``score``); only ``score`` without a validation split.
        best_score: best validation score of the run (lower is better).
        model: the trained model as it is in ``last.pt`` (in train mode, on the training device).
        best_step: the step whose validation wrote ``best.pt`` in this call (``None``: ``best.pt`` is from
            before a resume).
        best_metrics: that validation's metrics (as ``metrics``): the scores that belong to ``best.pt``.
        val_heights: the val split's valid reference pixels and those ≥ 2 m (what its height scores rest on;
            :mod:`aerialmtl.tiling.height_support`), ``None`` without a val split or heights (or off rank 0).
        val_cannot_judge: why that validation cannot judge heights (a phrase, also warned about), or ``None``.
    """

    run_dir: Path
    last_checkpoint: Path
    best_checkpoint: Path
    log_path: Path
    config_path: Path
    step: int
    epoch: int
    stopped_by: str
    elapsed_s: float
    metrics: dict[str, float] = field(default_factory=dict)
    best_score: float = math.inf
    model: torch.nn.Module | None = None
    best_step: int | None = None
    best_metrics: dict[str, float] = field(default_factory=dict)
    val_heights: TallCount | None = None
    val_cannot_judge: str | None = None


class Trainer(StepLoop):
    """Train a D3-Net on a tile folder; :meth:`fit` runs it (see :func:`aerialmtl.training.loop.train`).

    The step, the loss window and the ``train`` rows are the shared loop's
    (:class:`~aerialmtl.training.steploop.StepLoop`); the trainer adds the epochs, validation, ``best.pt``,
    early stopping, calibration and the feature density.

    Args:
        setup: what it trains with (:func:`~aerialmtl.training.setup.prepare_training`: model, optimiser,
            objective, loaders, the starting state), assembled before; the trainer writes ``config.yaml`` and
            the log, runs the loop and writes the checkpoints.
        max_steps, max_time_s: override ``schedule.max_steps`` / ``schedule.max_time_s``.
        progress: show a progress bar (rank 0 only).
    """

    def __init__(self, setup: TrainSetup, *, max_steps: int | None = None, max_time_s: float | None = None,
                 progress: bool = True) -> None:
        t0 = time.perf_counter()
        #: what it trains with; the properties below read it (nothing of it is copied)
        self.setup = setup
        cfg = setup.cfg
        #: the steps the learning-rate schedule spans: the config's (``schedule.max_steps``, else every epoch's),
        #: not this call's ``max_steps``, so a run stopped early and resumed follows the same schedule
        every_epoch = cfg.schedule.epochs * setup.loaders.order.steps_per_epoch
        planned = min(cfg.schedule.max_steps or every_epoch, every_epoch)
        self.paths = {n: setup.run / n for n in RUN_FILES}
        if setup.ctx.is_main:
            self.write_config(setup.data_dir if setup.data_dir is not None else cfg.data.dir)
        csv_log = CsvLog(self.paths["log.csv"], append=setup.resume) if setup.ctx.is_main else None
        parts = setup.parts
        super().__init__(cfg, setup.ctx, parts.model, parts.optimizer, parts.weighting, setup.ddp, setup.data.tasks,
                         setup.state, planned, csv_log, setup.averaged)
        self.t0 = t0
        self.steps_cap = max_steps if max_steps is not None else cfg.schedule.max_steps
        self.time_cap = max_time_s if max_time_s is not None else cfg.schedule.max_time_s
        self.progress = progress and self.ctx.is_main
        #: the losses validation scores with (setup's; a test may swap it for one trainer)
        self.objective = setup.objective
        #: step of the last checkpoint written whole (``last.pt``), or of the one resumed from
        self.saved_step: int | None = setup.saved_step
        self.metrics: dict[str, float] = {}
        #: the trained weights while the model holds their average for a checkpoint (``optim.ema``), else None
        self.raw_weights: dict[str, torch.Tensor] | None = None
        self.best_step: int | None = None  # the validation that wrote best.pt in this call, and its metrics
        self.best_metrics: dict[str, float] = {}
        self.validated_at = -1
        #: the sun fit running beside the steps (on an accelerator) until :meth:`fit_sun` collects it
        self.sun_beside: SunBeside | None = None
        #: the val split's reference pixels ≥ 2 m and why they cannot judge heights (rank 0; also warned about)
        self.val_heights, self.val_cannot_judge = self.check_validation_heights() if self.ctx.is_main else (None, None)

    # ---- what it trains with (read from the setup) --------------------------------------------------
    @property
    def device(self) -> torch.device:
        """The training device."""
        return self.setup.device

    @property
    def run(self) -> Path:
        """The run folder."""
        return self.setup.run

    @property
    def meta(self) -> ModelMeta:
        """The checkpoint metadata of the model trained."""
        return self.setup.data.meta

    @property
    def k(self) -> int | None:
        """The number of classes (``None`` without a classes task)."""
        return self.setup.data.k

    @property
    def order(self) -> EpochOrder:
        """The run's batch order."""
        return self.setup.loaders.order

    @property
    def val_loader(self) -> Batches | None:
        """The validation batches (``None`` without a val split)."""
        return self.setup.loaders.val_loader

    @property
    def height_slack(self) -> float:
        """The largest validation height MAE (m) a sane model of these heights reaches (:func:`height_slack`)."""
        return height_slack(self.meta.height_range)

    # ---- validation ---------------------------------------------------------------------------------
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Mean validation loss per task and height/classification metrics over the whole val split.

        Every process evaluates its share of the batches; sums are reduced, so the result is the same as
        one process evaluating all of them.

        Returns:
            ``val_loss_<task>``, and ``height_mae``/``height_rmse`` (metres) and/or ``oa``/``miou``. A task
            whose loss was NaN or inf on any batch has a non-finite ``val_loss_<task>`` (never a flattering 0).
        """
        assert self.val_loader is not None
        was_training = self.model.training
        self.model.eval()
        # every sum stays on the device until the pass ends: a GPU is not waited on batch by batch
        sums = torch.zeros(len(self.tasks) + 1, dtype=torch.float64, device=self.device)
        hm, cm = HeightMeter(self.device), ConfusionMeter(self.k or 2, self.device)
        loaders = self.setup.loaders
        for raw in self.val_loader:
            batch = prepare_batch(raw, loaders.eval_transform, loaders.mean, loaders.std, self.device)
            with runtime.autocast(self.device, self.setup.precision):
                out = self.model(batch["image"])
            losses = self.objective(out, batch, scoring=True)
            for i, t in enumerate(self.tasks):
                sums[i] += losses[t].detach().double()  # NaN/inf stays: a diverged model can never score best
            sums[-1] += 1
            if "height" in self.tasks:
                hm.update(out["height"].float(), batch["height"], batch["height_valid"])
            if "classes" in self.tasks:
                cm.update(out["classes"].float(), batch["classes"])
        self.model.train(was_training)
        self.ctx.all_reduce_sum(sums)
        totals = sums.tolist()
        metrics = {f"val_loss_{t}": totals[i] / max(1.0, totals[-1]) for i, t in enumerate(self.tasks)}
        if "height" in self.tasks:
            hm.sync(self.ctx.all_reduce_sum)
            metrics.update(hm.compute())
        if "classes" in self.tasks:
            cm.sync(self.ctx.all_reduce_sum)
            metrics.update(cm.compute())
        return metrics

    def check_validation_heights(self) -> tuple[TallCount | None, str | None]:
        """The val split's valid reference pixels and those ≥ 2 m (read from its patch cache), and why validation
        cannot judge heights (:func:`~aerialmtl.tiling.height_support.cannot_judge`: too few, or a far smaller
        share than train's), warned about with the fix. ``(None, None)`` without a val split or a height task.
        """
        data = self.setup.data
        if data.val_index is None or "height" not in self.tasks:
            return None, None
        train, val = cache_tall_count(data.cache_folder, "train"), cache_tall_count(data.cache_folder, "val")
        if train is None or val is None:
            return val, None
        message = validation_heights_warning(str(data.info.root), train, val, data.val_index.count)
        if message is not None:
            warnings.warn(message, UserWarning, stacklevel=2)
        return val, cannot_judge(train, val)

    def after_epoch_validation(self) -> bool:
        """Validate, log, and write best.pt/last.pt after an epoch.

        Without a val split the training loss scores the epoch. With ``optim.ema`` all of it runs with the weight
        average in the model.

        Returns:
            True when early stopping says to stop (``schedule.patience`` validations without improvement).
        """
        with self.averaged() as raw:
            self.raw_weights = raw
            try:
                return self._validate_and_save()
            finally:
                self.raw_weights = None  # a copy of every weight: not kept between validations

    def _validate_and_save(self) -> bool:
        """:meth:`after_epoch_validation` with the weights to judge in the model."""
        self.losses.flush()
        st = self.state
        if self.val_loader is not None:
            self.metrics = self.validate()
            current = {t: self.metrics[f"val_loss_{t}"] for t in self.tasks}
            st.ref_losses = reference = st.ref_losses or current
            score = validation_score(current, reference, self.objective.task_weights)
            self.losses.take_since_validation()
            measured = True
        else:
            measured = bool(self.losses.since_val)  # False: no step since the last score (inf, as before)
            score = self.losses.take_since_validation()
        self.metrics["score"] = score
        if self.csv_log is not None:
            self.csv_log.write(kind="val", step=st.step, epoch=st.epoch, time_s=self.elapsed(), lr=self.lr,
                               **{m: self.metrics.get(m) for m in LOG_COLUMNS if m in self.metrics})
        if measured and not math.isfinite(score):  # every process sees the same reduced score, so all stop together
            bad = [t for t in self.tasks if not math.isfinite(self.metrics.get(f"val_loss_{t}", 0.0))]
            raise NonFiniteError(
                f"training diverged: the validation score at step {st.step} is {score}"
                f"{' (' + ', '.join(bad) + ' loss)' if bad else ''}; best.pt keeps the best finite score; "
                f"{self.recovery_hint()}"
            )
        if measured:
            self.check_exploded(st.step)
        improved = score < st.best_score
        if improved or not self.paths["best.pt"].exists():
            st.best_score = min(st.best_score, score)
            self.checkpoint(self.paths["best.pt"])
            self.best_step, self.best_metrics = st.step, dict(self.metrics)
        st.since_best = 0 if improved else st.since_best + 1
        self.checkpoint(self.paths["last.pt"])
        patience = self.cfg.schedule.patience
        return patience is not None and st.since_best >= patience

    def check_exploded(self, step: int) -> None:
        """Stop like a non-finite run when the validation error is finite but can only be garbage.

        Garbage: a height MAE beyond :attr:`height_slack` (10 × the trained height span + 100 m), or a class
        loss above :data:`EXPLODED_CLASS_LOSS` × ln K (an untrained model scores ln K). Every process sees the
        same reduced metrics, so all stop together; ``best.pt`` and ``last.pt`` are not replaced.

        Raises:
            NonFiniteError: naming the step, the value, the bound and what to do.
        """
        kept = ("best.pt keeps the best earlier score" if self.paths["best.pt"].exists()
                else "it was not saved as best.pt")
        mae = self.metrics.get("height_mae")
        if mae is not None and mae > self.height_slack:
            trained = (f"reference heights of {self.meta.height_range[0]:.4g}..{self.meta.height_range[1]:.4g} m"
                       if self.meta.height_range is not None else "reference heights")
            raise NonFiniteError(
                f"training diverged: the validation height MAE at step {step} is {mae:.3g} m, more than "
                f"{self.height_slack:.4g} m for {trained}, so {kept}; "
                f"{self.recovery_hint()}")
        ce = self.metrics.get("val_loss_classes")
        bound = EXPLODED_CLASS_LOSS * math.log(max(self.k or 2, 2))
        if ce is not None and ce > bound:
            raise NonFiniteError(
                f"training diverged: the validation class loss at step {step} is {ce:.3g}, more than {bound:.3g} "
                f"({EXPLODED_CLASS_LOSS:g} × ln {self.k}, what an untrained model scores), so {kept}; "
                f"{self.recovery_hint()}")

    # ---- checkpoints --------------------------------------------------------------------------------
    def recovery_hint(self) -> str:
        """What to do after a divergence: where the last whole checkpoint is, and how to continue.

        When the tile folder's reference heights are ones no surface has, that comes first: no learning rate
        fixes them.
        """
        hr = self.meta.height_range
        if hr is not None and (hr[0] < SURFACE_HEIGHTS_M[0] or hr[1] > SURFACE_HEIGHTS_M[1]):
            return (f"the tile folder's reference heights reach {hr[0]:.3g}..{hr[1]:.3g} m, which no surface has "
                    "(an undeclared nodata value or a wrong unit in the DSM/DTM/nDSM): fix the height files "
                    "(`gdal_edit.py -a_nodata VALUE FILE`, --z-unit) and run `aerialmtl tile ... --overwrite` again")
        last = self.paths["last.pt"]
        lower = f"lower optim.lr (now {self.cfg.optim.lr:g}; e.g. {self.cfg.optim.lr / 10:g})"
        if self.saved_step is not None and last.exists():
            return (f"'{last}' (step {self.saved_step}) is the last good state, unchanged: {lower} in "
                    f"'{self.paths['config.yaml']}' and continue with `aerialmtl train --out {self.run} --resume`, "
                    "use precision fp32, or check the tile folder's images and references")
        return (f"no checkpoint was written; {lower}, use precision fp32, or check the tile folder's images and "
                "references, then start again")

    def counters(self, rngs: list[dict[str, Any]]) -> dict[str, Any]:
        """The counters, early stopping and every process's RNG state (see :mod:`aerialmtl.training.state`)."""
        gb = self.order.global_batch
        return {**self.state.to_dict(gb), "rng": rngs[0], "rng_ranks": rngs, "world_size": self.ctx.world,
                "global_batch": gb}

    def checkpoint(self, target: Path) -> None:
        """Write ``target`` (``best.pt`` or ``last.pt``) with the full training state (:meth:`StepLoop.save`).

        Every process must call it; with ``optim.ema`` ``last.pt`` keeps the trained weights beside the average.
        """
        last = target == self.paths["last.pt"]
        self.save(target, self.meta, self.raw_weights if last else None)
        if last:
            self.saved_step = self.state.step

    def write_config(self, data: str | Path | None) -> None:
        """``config.yaml``: the config with the model fields taken from the data and the absolute data dir."""
        cfg = self.setup.cfg
        resolved = cfg.to_dict()
        resolved["model"] = {**to_dict(self.setup.data.model_cfg), "sync_bn": cfg.model.sync_bn}
        resolved["data"]["dir"] = str(Path(data).resolve()) if data is not None else None
        with writing(self.paths["config.yaml"], "the run's config"):
            RunFolder(self.run).write_config(resolved)

    # ---- the loop -----------------------------------------------------------------------------------
    def advance(self) -> None:
        """The epoch and position after a step."""
        st = self.state
        st.epoch, st.position = self.order.advance(st.epoch, st.position)

    def after_step(self) -> str | None:
        """Validate at the end of every ``val_every``-th epoch; why to stop (``patience`` or :meth:`done`)."""
        st = self.state
        if st.position == 0 and st.epoch % self.cfg.schedule.val_every == 0:
            self.validated_at = st.step
            if self.after_epoch_validation():
                return "patience"
        return self.done()

    def done(self) -> str | None:
        """Why training must stop now (``max_steps``, ``epochs``, ``max_time``), or ``None``."""
        st = self.state
        if self.steps_cap is not None and st.step >= self.steps_cap:
            return "max_steps"
        if st.epoch >= self.cfg.schedule.epochs:
            return "epochs"
        if self.time_cap is not None and self.ctx.any(time.perf_counter() - self.t0 >= self.time_cap):
            return "max_time"
        return None

    def fit(self) -> TrainResult:
        """Train until a stop condition (each process returns the same counters and metrics).

        On an accelerator the training area's sun is fitted in a process of its own beside the steps
        (:mod:`aerialmtl.training.sun_beside`), and collected after calibration and the feature density.
        """
        stopped_by = self.done_before_start()
        try:
            if self.sun_wanted and self.setup.sun is None and beside_steps(self.device.type):
                self.sun_beside = SunBeside(self.setup.data.info.root)
            return self._fit(stopped_by)
        finally:
            if self.sun_beside is not None:  # failed or interrupted before the sun was collected
                self.sun_beside.stop()

    def _fit(self, stopped_by: str | None) -> TrainResult:
        """:meth:`fit`'s steps, then the last validation, calibration, feature density and sun."""
        st, sched = self.state, self.cfg.schedule
        nb = self.order.steps_per_epoch
        total = sched.epochs * nb if self.steps_cap is None else min(self.steps_cap, sched.epochs * nb)
        self.validated_at = -1
        self.model.train()
        bar = tqdm(total=total, initial=min(st.step, total), disable=not self.progress, desc="train", unit="step",
                   dynamic_ncols=True)
        loaders = self.setup.loaders
        it = iter(loaders.train_loader) if stopped_by is None else None
        batches = None if it is None else (
            prepare_batch(raw, loaders.train_transform, loaders.mean, loaders.std, self.device) for raw in it)
        try:
            if batches is not None:
                stopped_by = self.run_steps(batches, bar)
        except RuntimeError as exc:  # DDP's gradient all-reduce: a peer process is gone
            if self.ctx.distributed and runtime.is_peer_error(exc):
                raise runtime.peer_failure(exc) from exc
            raise
        finally:
            bar.close()
            del batches, it  # the loader's workers (or, on a CPU, its thread) end here, before the last validation
        if self.validated_at != st.step or not self.paths["last.pt"].exists():
            self.after_epoch_validation()
        if self.average is not None:  # the run is over: the model is its average, as in last.pt
            self.model.load_state_dict(self.average.shadow)
        self.calibrate()
        self.familiarize()
        self.fit_sun()
        assert stopped_by is not None  # the loop ran until a reason, or there was one before it
        return TrainResult(run_dir=self.run, last_checkpoint=self.paths["last.pt"],
                           best_checkpoint=self.paths["best.pt"], log_path=self.paths["log.csv"],
                           config_path=self.paths["config.yaml"], step=st.step, epoch=st.epoch, stopped_by=stopped_by,
                           elapsed_s=time.perf_counter() - self.t0, metrics=self.metrics, best_score=st.best_score,
                           model=self.model, best_step=self.best_step, best_metrics=self.best_metrics,
                           val_heights=self.val_heights, val_cannot_judge=self.val_cannot_judge)

    def calibrate(self) -> None:
        """Fit the calibration on the val split and store it in best.pt and last.pt.

        Runs on rank 0 (see :mod:`aerialmtl.training.calibrate`); skipped without a val split or a height task.
        """
        cal = self.cfg.calibration
        if not (cal.enabled and self.ctx.is_main and self.val_loader is not None and "height" in self.tasks):
            return
        data = self.setup.data
        n = data.val_index.count if data.val_index is not None else 0
        what = f"calibration on the {n} validation patches ({cal.mc_samples} MC-dropout samples each)"
        self.fit_per_network("calibration", what,
                             lambda path: calibrate_checkpoint(
                                 path, data.info.root, mc=cal.mc_samples, method=cal.method,
                                 cache_folder=data.cache_folder, device=self.device, progress=self.progress))

    def familiarize(self) -> None:
        """Fit the encoder-feature density on the train split and store it in best.pt and last.pt.

        Runs on rank 0 (see :mod:`aerialmtl.training.familiarity`).
        """
        fam = self.cfg.familiarity
        if not (fam.enabled and self.ctx.is_main):
            return
        data = self.setup.data
        self.fit_per_network("familiarity", f"feature density on the {data.train_index.count} training patches",
                             lambda path: familiarize_checkpoint(
                                 path, data.info.root, levels=fam.levels, dims=fam.dims, method=fam.method,
                                 components=fam.components, cache_folder=data.cache_folder, device=self.device,
                                 progress=self.progress))

    def fit_per_network(self, record: str, what: str, fit: Callable[[Path], Calibration | FeatureDensity]) -> None:
        """``fit(path)`` each of best.pt and last.pt (it stores the result as meta ``record``), once per network.

        When the run's last validation was its best, both hold the same network
        (:func:`~aerialmtl.formats.checkpoint.same_weights`): the second gets the first's result (each fit is
        deterministic: seeded MC passes and samples), not a second fit. Each fit starts with a line saying
        ``what`` it fits (:func:`~aerialmtl.progress.announce`, with the progress bar) and ends with one log line
        per checkpoint.
        """
        fitted: list[tuple[Path, Calibration | FeatureDensity]] = []
        for name in ("best.pt", "last.pt"):
            path = self.paths[name]
            if not path.exists():
                continue
            result = next((r for p, r in fitted if same_weights(p, path)), None)
            if result is not None:
                update_meta(path, None, **{record: result})
            else:
                announce(f"{name}: {what}", self.progress)
                result = fit(path)
            fitted.append((path, result))
            log.info("%s: %s", name, result.summary())

    @property
    def sun_wanted(self) -> bool:
        """Whether this process fits the training area's sun (``sun.enabled``, rank 0, a height task)."""
        return self.cfg.sun.enabled and self.ctx.is_main and "height" in self.tasks

    def fit_sun(self) -> None:
        """Fit the training area's sun and shadow classifier and store them in best.pt and last.pt.

        Runs on rank 0 (see :mod:`aerialmtl.training.sun`); one line says the sun, or why there is none.
        """
        if not self.sun_wanted:
            return
        beside, self.sun_beside = self.sun_beside, None
        announce(f"sun fit on the {self.setup.data.train_index.count} training patches (best.pt, last.pt)"
                 + ("" if beside is None else ": collecting the fit that ran beside the steps"), self.progress)
        try:
            sun = (self.setup.sun if self.setup.sun is not None  # fitted before the steps (the shadow head)
                   else fit_training_sun(self.setup.data.info.root, progress=self.progress) if beside is None
                   else beside.result())
        except InputError as exc:
            log.info("no sun fitted: %s", exc)
            return
        for name in ("best.pt", "last.pt"):
            if self.paths[name].exists():
                store_sun(self.paths[name], sun)
        log.info("%s", sun.summary())

    def done_before_start(self) -> str | None:
        """Stop reason of a resumed run that has nothing left to do (no time check: it has not started)."""
        st = self.state
        if self.steps_cap is not None and st.step >= self.steps_cap:
            return "max_steps"
        if st.epoch >= self.cfg.schedule.epochs:
            return "epochs"
        return None

    def close(self) -> None:
        """Release the process group if this trainer created it."""
        if self.setup.owns_ctx:
            self.ctx.leave()


__all__ = ["LOSS_GROWTH", "Trainer", "TrainResult", "LossWindow",
           "RUN_FILES"]
