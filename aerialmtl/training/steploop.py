"""The optimisation-step loop every training command runs.

``aerialmtl train`` runs it on a tile folder and ``aerialmtl pretrain`` on a synthetic stream (pretraining is
training on another stream of batches).

:class:`StepLoop` owns what a step is and what happens around it, once:

* the step (:meth:`StepLoop.train_step`): the learning rate of ``schedule.lr_schedule`` and
  ``schedule.warmup_steps`` (:func:`~aerialmtl.training.lr_schedule.lr_factor`, a pure function of the step),
  forward + losses + task weighting (the step module, DDP-wrapped with several processes), backward, the
  optimiser, and the weight average of ``optim.ema`` (:class:`~aerialmtl.training.averaging.WeightAverage`);
* the losses (:class:`LossWindow`): kept on the device, read only when a row is logged or before a checkpoint,
  and checked there for a non-finite loss or one grown by :data:`LOSS_GROWTH` (divergence);
* the ``train`` rows of ``log.csv`` every ``schedule.log_every`` steps, with the learning rate the step used;
* the loop (:meth:`StepLoop.run_steps`): batches → step → window → row, and the command's own ``after_step``
  (the trainer's epochs and validations, pretraining's checkpoints) until it says why to stop;
* the checkpoint (:meth:`StepLoop.save`): refused while a weight is not finite, the optimiser, the task
  weighting, the config and the command's own counters and RNG states (:meth:`StepLoop.counters`), the trained
  weights beside their average (``optim.ema``), written by rank 0. Resuming it is
  :mod:`aerialmtl.training.resume`'s, the run folder's policy :mod:`aerialmtl.training.run_folder`'s.

So every ``optim``/``schedule`` key that concerns steps means the same in both commands, and a diverging run
stops in both.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl.errors import NonFiniteError
from aerialmtl.formats.checkpoint import ModelMeta, first_nonfinite, save_checkpoint
from aerialmtl.formats.run import RAW_WEIGHTS_KEY, CsvLog
from aerialmtl.training.averaging import WeightAverage
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.lr_schedule import lr_factor
from aerialmtl.training.state import TrainState, rng_state

#: A task loss this many times its first logged value means the run diverged (finite or not).
LOSS_GROWTH = 1e4


class LossWindow:
    """Per-step losses kept on the device, read only when logged or before a validation.

    A read is one synchronisation, reduced over processes; reading after every step would stall a GPU.

    ``flush`` checks every pending step for a non-finite loss, or a task loss that grew by more than
    :data:`LOSS_GROWTH` times its first logged value (a diverged-but-finite run), and raises naming the first
    one (with ``hint()``, what to do, appended).
    """

    def __init__(self, tasks: tuple[str, ...], ctx: runtime.Torchrun, hint: Callable[[], str] | None = None) -> None:
        self.tasks, self.ctx = tasks, ctx
        self.hint = hint if hint is not None else (lambda: "")
        self.pending: list[torch.Tensor] = []
        self.first_step = 0
        self.window: dict[str, list[float]] = {"loss": [], **{t: [] for t in tasks}}
        self.since_val: list[float] = []
        #: each task's first logged loss (the untrained model's, or the resumed one's): the growth reference
        self.first: dict[str, float] = {}

    def add(self, step: int, total: torch.Tensor, losses: dict[str, torch.Tensor]) -> None:
        """Keep the losses of ``step`` (on the device, not read yet)."""
        if not self.pending:
            self.first_step = step
        self.pending.append(torch.stack([total.float()] + [losses[t].float() for t in self.tasks]))

    def flush(self) -> None:
        """Read the pending losses (one synchronisation) and raise on the first non-finite one."""
        if not self.pending:
            return
        values = self.ctx.all_reduce_sum(torch.stack(self.pending)) / self.ctx.world
        rows = values.cpu().tolist()
        first = self.first_step
        self.pending = []
        for i, row in enumerate(rows):
            if not math.isfinite(row[0]):
                tasks = [t for t, v in zip(self.tasks, row[1:]) if not math.isfinite(v)]
                which = f" ({', '.join(tasks)})" if tasks else ""
                raise NonFiniteError(f"training diverged at step {first + i}: the loss is {row[0]}{which}; "
                                     f"{self.hint()}")
            for t, v in zip(self.tasks, row[1:]):
                ref = self.first.setdefault(t, v)
                if ref > 0 and v > LOSS_GROWTH * ref:
                    raise NonFiniteError(f"training diverged at step {first + i}: the {t} loss grew from {ref:.3g} "
                                         f"to {v:.3g} (more than {LOSS_GROWTH:.0e} times); {self.hint()}")
            self.window["loss"].append(row[0])
            self.since_val.append(row[0])
            for t, v in zip(self.tasks, row[1:]):
                self.window[t].append(v)

    def take(self) -> dict[str, float]:
        """Means since the last ``take`` (after a flush); resets the window."""
        means = {k: float(np.mean(v)) for k, v in self.window.items() if v}
        self.window = {k: [] for k in self.window}
        return means

    def take_since_validation(self) -> float:
        """Mean total loss since the last validation (``inf`` without any); starts a new window."""
        value = float(np.mean(self.since_val)) if self.since_val else math.inf
        self.since_val = []
        return value


class StepLoop:
    """The step and the loop of a training command (see the module docstring).

    The trainer and pretraining are subclasses that say where batches come from and what happens after a step
    (:meth:`after_step`).

    Args:
        cfg: the training configuration (``optim.lr``, ``optim.ema``, ``schedule.lr_schedule``,
            ``schedule.warmup_steps``, ``schedule.log_every``).
        ctx: the process context.
        model: the model trained; ``optimizer`` steps it (and the task weighting ``weighting``).
        step_module: one step's forward, losses and task weighting ``batch → (total, {task: loss})``
            (DDP-wrapped with several processes).
        tasks: the tasks trained, in the log's order.
        state: the counters (``step`` is advanced here; the rest by the subclass).
        planned_steps: the steps the learning-rate schedule spans (the cosine reaches its end there).
        csv_log: the run's ``log.csv`` (``None`` on processes other than rank 0).
        averaged: a saved weight average to continue (``optim.ema`` on resume), else the model's weights.
    """

    def __init__(self, cfg: TrainConfig, ctx: runtime.Torchrun, model: nn.Module, optimizer: torch.optim.Optimizer,
                 weighting: nn.Module, step_module: nn.Module, tasks: tuple[str, ...], state: TrainState,
                 planned_steps: int, csv_log: CsvLog | None, averaged: dict[str, torch.Tensor] | None = None) -> None:
        self.cfg, self.ctx, self.model, self.optimizer, self.weighting = cfg, ctx, model, optimizer, weighting
        self.step_module, self.tasks, self.state = step_module, tasks, state
        self.planned_steps, self.csv_log = planned_steps, csv_log
        self.t0 = time.perf_counter()
        self.average: WeightAverage | None = None
        if cfg.optim.ema is not None:
            self.average = WeightAverage(model, cfg.optim.ema)
            if averaged is not None:
                self.average.load(averaged)
        self.losses = LossWindow(tasks, ctx, self.recovery_hint)

    # ---- the step -----------------------------------------------------------------------------------
    def train_step(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One optimisation step on a prepared batch; returns the detached total and task losses."""
        sched = self.cfg.schedule
        lr = self.cfg.optim.lr * lr_factor(self.state.step, self.planned_steps, sched.lr_schedule, sched.warmup_steps)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        total, losses = self.step_module(batch)
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()
        if self.average is not None:
            self.average.update(self.model)
        return total.detach(), {t: v.detach() for t, v in losses.items()}

    def averaged(self) -> contextlib.AbstractContextManager[dict[str, torch.Tensor] | None]:
        """A block in which the model holds the weight average (``optim.ema``); yields the raw weights.

        Yields ``None`` without an average, when the model is used as it is.
        """
        return self.average.applied(self.model) if self.average is not None else contextlib.nullcontext()

    # ---- the log ------------------------------------------------------------------------------------
    @property
    def lr(self) -> float:
        """The learning rate of the last step."""
        return float(self.optimizer.param_groups[0]["lr"])

    def elapsed(self) -> float:
        """The ``time_s`` of a log row: seconds since this call started."""
        return round(time.perf_counter() - self.t0, 3)

    def recovery_hint(self) -> str:
        """What to do after a divergence (appended to the error)."""
        return f"lower optim.lr (now {self.cfg.optim.lr:g})"

    def log_train_row(self) -> dict[str, float]:
        """Write the ``train`` row of the steps since the last one; returns its mean losses."""
        self.losses.flush()
        means = self.losses.take()
        if self.csv_log is not None and means:
            self.csv_log.write(kind="train", step=self.state.step, epoch=self.state.epoch, time_s=self.elapsed(),
                               lr=self.lr, loss=means["loss"], **{f"loss_{t}": means.get(t) for t in self.tasks})
        return means

    # ---- the checkpoint -----------------------------------------------------------------------------
    def counters(self, rngs: list[dict[str, Any]]) -> dict[str, Any]:
        """The command's own part of a checkpoint's ``train_state``: its counters and the RNG states ``rngs``
        (one per process, rank 0's first) it resumes with.
        """
        raise NotImplementedError

    def save(self, target: Path, meta: ModelMeta, raw: dict[str, torch.Tensor] | None = None) -> None:
        """Write checkpoint ``target`` with the model as it is and the whole training state.

        Every process must call it (the RNG states are gathered); rank 0 writes. ``raw``: the trained weights
        while the model holds their average (``optim.ema``), stored beside it for training to continue from.

        Raises:
            NonFiniteError: a weight is NaN or inf (checked on every process, so all stop together); the file
                stays as it was.
        """
        bad = first_nonfinite(self.model.state_dict())
        if bad is not None:
            raise NonFiniteError(f"training diverged at step {self.state.step}: weight '{bad}' holds NaN or inf; "
                                 f"{self.recovery_hint()}")
        rngs = self.ctx.gather(rng_state())
        if not self.ctx.is_main:
            return
        state = {"optimizer": self.optimizer.state_dict(), "weighting": self.weighting.state_dict(),
                 **self.counters(rngs), "config": self.cfg.to_dict()}
        if raw is not None:
            state[RAW_WEIGHTS_KEY] = raw
        save_checkpoint(target, self.model, meta, state)

    # ---- the loop -----------------------------------------------------------------------------------
    def advance(self) -> None:
        """Move the command's own counters after a step (before its row is logged); nothing by default."""

    def after_step(self) -> str | None:
        """After a step and its row: the command's own work (validation, checkpoints); why to stop, or None."""
        return None

    def run_steps(self, batches: Iterator[dict[str, Any]], bar: Any) -> str:
        """Step through ``batches`` (prepared, on the device) until :meth:`after_step` names a reason to stop.

        Args:
            batches: the prepared batches, one per step.
            bar: a progress bar (``update``, ``set_postfix``).

        Returns:
            The reason :meth:`after_step` gave.
        """
        st, every = self.state, self.cfg.schedule.log_every
        while True:
            total, losses = self.train_step(next(batches))
            st.step += 1
            self.losses.add(st.step, total, losses)
            self.advance()
            bar.update(1)
            if st.step % every == 0:
                means = self.log_train_row()
                bar.set_postfix(loss=f"{means.get('loss', math.nan):.4f}", epoch=st.epoch)
            stop = self.after_step()
            if stop is not None:
                return stop


__all__ = ["LOSS_GROWTH", "LossWindow", "StepLoop"]
