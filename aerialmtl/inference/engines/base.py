"""The interface of the engines.

:class:`Engine`, what :meth:`Engine.submit` returns (:class:`Pending`), and what an engine is built from
(:class:`EngineSetup`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch
from torch import nn

from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.model_record import CheckpointModel
from aerialmtl.inference.settings import PredictSettings, ResolvedSettings
from aerialmtl.models.mc_dropout import McStatistics


@dataclass(frozen=True)
class EngineSetup:
    """What an engine is built from (:func:`~aerialmtl.inference.engines.registry.build_engine`).

    Attributes:
        model: the loaded model (each engine prepares its own copy: folded BatchNorms, channels-last), or a
            :class:`~aerialmtl.inference.model_record.CheckpointModel` (loaded only when the engine needs
            the weights).
        meta: its checkpoint metadata (input bands, tasks).
        settings: predict's settings, as the caller built them (``compile``, ...).
        resolved: the device, engine, precision and threads they resolved to.
        weights_key: the checkpoint's fingerprint, when the caller has it (keys caches without hashing the
            weights again).
    """

    model: nn.Module | CheckpointModel
    meta: ModelMeta
    settings: PredictSettings
    resolved: ResolvedSettings
    weights_key: str | None = None

    @property
    def tasks(self) -> tuple[str, ...]:
        """The model's tasks."""
        return tuple(self.meta.model.tasks)


class Engine(Protocol):
    """What runs the model in prediction: the one interface of every engine.

    ``torch``: :class:`~aerialmtl.inference.engines.torch_engine.TorchEngine`, ``openvino``:
    :class:`~aerialmtl.inference.engines.openvino_engine.OpenVINOEngine`.

    The runner (:class:`~aerialmtl.inference.runner.ModelRunner`) uses these members only; it never asks
    which class it holds. A new engine implements them in a module of its own and is one entry of
    :data:`~aerialmtl.inference.engines.registry.ENGINES`.
    """

    #: The engine's name in :data:`~aerialmtl.inference.engines.registry.ENGINES` (recorded in ``prediction.json``).
    name: str

    @property
    def model(self) -> nn.Module:
        """The engine's own copy of the model, prepared for prediction (the fallback and the tests use it)."""
        ...

    @property
    def net(self) -> nn.Module:
        """A torch module that computes what the engine computes.

        For measuring the memory of one window (:func:`~aerialmtl.inference.runner.auto_batch_size` on CUDA).
        """
        ...

    def ahead(self, samples: int) -> int:
        """Batches a caller may keep submitted (:meth:`submit`) ahead of the one it stitches.

        At ``samples`` MC samples; 0 for an engine that computes synchronously.
        """
        ...

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        """Statistics of each window of a normalised batch.

        Args:
            x: (B, C, h, w) normalised windows, on the engine's device.
            keys: one dropout-mask key per window (masks depend on the window, not on the batch).
            samples: MC-dropout samples T (1: one deterministic pass).
            seed: the run's seed of the dropout masks.
            sample_batch: MC samples decoded per call (bounds memory, not results).

        Returns:
            per-window height mean/std (B, h, w, metres), class probabilities (B, h, w, K) and mean
            per-sample entropy, as :class:`~aerialmtl.models.mc_dropout.McStatistics`.
        """
        ...

    def submit(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
               sample_batch: int) -> Pending:
        """Start :meth:`statistics` of a batch; ``.result()`` of the returned :class:`Pending` gives them.

        An engine that runs synchronously returns them computed, as :class:`Done`.
        """
        ...



@dataclass(frozen=True)
class EngineSpec:
    """One engine of the registry: its module's ``SPEC`` (:mod:`aerialmtl.inference.engines.names`).

    What the engine supports and what it is expected to cost, declared here, is all that ``auto``
    (:func:`~aerialmtl.inference.engine_choice.auto_engine`) knows of it besides the measured table.

    Attributes:
        name: the ``engine`` value that selects it (recorded in ``prediction.json``).
        label: how messages spell it (``OpenVINO``).
        build: setup → the engine.
        unusable: (device, model) → why the engine cannot run that model there (the error to raise), or ``None``.
        over: (model another engine prepared, setup) → the engine over that model, not compiled; what ``auto``'s
            fallback builds (needed of :data:`~aerialmtl.inference.engines.names.FALLBACK` only).
        speedup: the expected end-to-end speed over the torch engine at fp32 on a CPU whose kind the measured
            table (:mod:`~aerialmtl.inference.engine_choice`) has no entry for, or does not name the engine in;
            1.0 claims nothing (the torch engine's own).
        compile_mpx: what compiling one graph costs before the first window (0: nothing compiled), in window
            megapixels of the torch engine at fp32 on the same CPU.
        cached: (setup, window shapes ``(h, w)``, MC samples) → whether every graph a job of those runs is compiled
            in the engine's cache already (``None``: the engine keeps no cache; its ``compile_mpx`` is always paid).
        record_root: → the folder that holds checkpoint records beside the engine's cache
            (:mod:`~aerialmtl.inference.model_record`), ``None`` where there is none; an engine that has one
            runs from the record without loading the weights, and its cache is keyed by the checkpoint's hash.
        bf16_needs_amx: ``precision=auto`` takes bf16 on a CPU only with AMX (the torch engine), rather than
            wherever the CPU has native bf16.
        takes_compile: the ``compile`` setting (torch.compile) applies to it.
        precisions: the precisions ``aerialmtl bench`` measures it at.
        layout: what ``prediction.json`` records as its layout (``None``: the engine picks its own; its name).
    """

    name: str
    label: str
    build: Callable[[EngineSetup], Engine]
    unusable: Callable[[torch.device, nn.Module | CheckpointModel], InputError | None]
    over: Callable[[nn.Module, EngineSetup], Engine] | None = None
    speedup: float = 1.0
    compile_mpx: float = 0.0
    cached: Callable[[EngineSetup, Collection[tuple[int, int]], int], bool] | None = None
    record_root: Callable[[], Path | None] | None = None
    bf16_needs_amx: bool = False
    takes_compile: bool = False
    precisions: tuple[str, ...] = ("fp32", "bf16")
    layout: str | None = None


class Pending(Protocol):
    """Statistics of a batch being computed; :meth:`result` waits for them."""

    def result(self) -> McStatistics:
        """The statistics, once computed (waits for them)."""
        ...


class Done:
    """Statistics already computed (the torch engine's, which runs synchronously)."""

    def __init__(self, stats: McStatistics) -> None:
        self.stats = stats

    def result(self) -> McStatistics:
        """The statistics."""
        return self.stats


class Deferred:
    """Statistics computed when asked for."""

    def __init__(self, compute: Callable[[], McStatistics]) -> None:
        self.compute = compute

    def result(self) -> McStatistics:
        """The statistics, computed now."""
        return self.compute()




__all__ = ["Deferred", "Done", "Engine", "EngineSetup", "EngineSpec", "Pending"]
