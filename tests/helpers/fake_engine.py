"""A third engine for the tests, written as docs/CONTRACTS.md says an engine is added: this one module (a class with
the :class:`~aerialmtl.inference.engines.base.Engine` members, a function building it from an ``EngineSetup``, one
saying why it cannot run somewhere, and its :data:`SPEC`) plus one entry naming this module in
``aerialmtl.inference.engines.names.ENGINE_MODULES``, which a test adds. It computes with the torch engine's model and
counts the windows it was given, so a test can tell that it, and not another engine, made the maps.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from aerialmtl.errors import InputError
from aerialmtl.inference.engines import Done, EngineSetup, EngineSpec, Pending, TorchEngine
from aerialmtl.inference.engines.torch_engine import build_torch
from aerialmtl.inference.model_record import CheckpointModel
from aerialmtl.models.mc_dropout import McStatistics

NAME = "counting"


class CountingEngine:
    """The torch engine's maps, synchronously, counting the windows computed."""

    name = NAME

    def __init__(self, inner: TorchEngine) -> None:
        self.inner = inner
        self.windows = 0

    @property
    def model(self) -> nn.Module:
        return self.inner.model

    @property
    def net(self) -> nn.Module:
        return self.inner.net

    def ahead(self, samples: int) -> int:
        return 0

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        self.windows += len(keys)
        return self.inner.statistics(x, keys, samples, seed, sample_batch)

    def submit(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int, sample_batch: int) -> Pending:
        return Done(self.statistics(x, keys, samples, seed, sample_batch))


#: Every engine built, in order (the tests read the last one's count).
BUILT: list[CountingEngine] = []


def build_counting(setup: EngineSetup) -> CountingEngine:
    engine = CountingEngine(build_torch(setup))
    BUILT.append(engine)
    return engine


def counting_unusable(device: torch.device, model: nn.Module | CheckpointModel) -> InputError | None:
    if device.type != "cpu":
        return InputError(f"‹engine={NAME}› runs on the CPU, not on {device}; pass ‹device=cpu›", param="engine")
    return None


#: The engine's entry of the registry.
SPEC = EngineSpec(NAME, "counting", build_counting, counting_unusable)
