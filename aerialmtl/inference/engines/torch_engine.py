"""The ``torch`` engine: the model in PyTorch (eager, or ``torch.compile``), on any device; CUDA's only one."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import cast

import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl.errors import InputError
from aerialmtl.inference.engines.base import Done, EngineSetup, EngineSpec, Pending
from aerialmtl.inference.model_record import CheckpointModel, resolve_model
from aerialmtl.models.d3net import decode_features, encode_features, inference_model
from aerialmtl.models.familiarity import FeatureDensity
from aerialmtl.models.mc_dropout import McStatistics, mc_statistics, single_pass_statistics


class _Compiled(nn.Module):
    """``torch.compile`` of the deterministic parts (``forward`` for T = 1, ``encode`` for MC).

    With the fallback of :class:`aerialmtl.runtime.CompileFallback`.

    The decoder stays eager under MC dropout: its per-window seeded masks are drawn by Python hooks.
    """

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model
        self._compiled = runtime.CompileFallback(model, "the model")

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        return cast(list[torch.Tensor], self._compiled("encode", x))

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        decode: Callable[[list[torch.Tensor]], dict[str, torch.Tensor]] = getattr(self.model, "decode")  # noqa: B009
        return decode(feats)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return cast(dict[str, torch.Tensor], self._compiled("forward", x))


def compile_model(model: nn.Module) -> nn.Module:
    """The model with ``torch.compile`` applied where it can be (see :class:`_Compiled`)."""
    return _Compiled(model)


class TorchEngine:
    """The model in PyTorch (eager, or ``torch.compile``), on any device: today's path and CUDA's only one.

    Args:
        net: the prepared model (:func:`~aerialmtl.models.d3net.inference_model`), or its compiled wrapper
            (:func:`compile_model`).
        model: the prepared model itself (its modes are switched for MC dropout).
        device, precision: where and how it runs (bf16 = autocast).
        tasks: the model's tasks.
        density: the checkpoint's feature density: each window's ``unfamiliarity`` from its encoder features.
    """

    name = "torch"

    def __init__(self, net: nn.Module, model: nn.Module, device: torch.device, precision: str,
                 tasks: Sequence[str], density: FeatureDensity | None = None) -> None:
        self._net, self._model = net, model
        self.device, self.precision, self.tasks = device, precision, tuple(tasks)
        self.density = density

    @property
    def model(self) -> nn.Module:
        """The prepared model."""
        return self._model

    @property
    def net(self) -> nn.Module:
        """What the engine calls: the prepared model, or its compiled wrapper."""
        return self._net

    def ahead(self, samples: int) -> int:
        """None: torch computes synchronously."""
        return 0

    def submit(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int, sample_batch: int) -> Pending:
        """:meth:`statistics`, computed now (torch runs synchronously)."""
        return Done(self.statistics(x, keys, samples, seed, sample_batch))

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        """Normalised (B, C, h, w) batch → statistics of each window (see :class:`McStatistics`)."""
        with torch.inference_mode(), runtime.autocast(self.device, self.precision):
            if samples == 1:
                self._model.eval()
                if self.density is None:
                    return single_pass_statistics(self._net(x))
                feats = encode_features(self._net, x)
                stats = single_pass_statistics(decode_features(self._net, feats))
                stats.unfamiliarity = self.density.unfamiliarity(feats, (x.shape[-2], x.shape[-1]))
                return stats
            return mc_statistics(self._net, x, samples, sample_batch=sample_batch, seed=seed, keys=keys,
                                 density=self.density)



def build_torch(setup: EngineSetup) -> TorchEngine:
    """The torch engine of ``setup``.

    The model prepared (:func:`~aerialmtl.models.d3net.inference_model`), compiled with ``settings.compile``.
    """
    device = setup.resolved.device
    prepared = inference_model(resolve_model(setup.model), device)
    net = compile_model(prepared) if setup.settings.compile else prepared
    return TorchEngine(net, prepared, device, setup.resolved.precision, setup.tasks, density=setup.meta.familiarity)


def torch_over(model: nn.Module, setup: EngineSetup) -> TorchEngine:
    """The torch engine over a model another engine prepared already (the fallback: not compiled)."""
    return TorchEngine(model, model, setup.resolved.device, setup.resolved.precision, setup.tasks,
                       density=setup.meta.familiarity)


def _always_usable(device: torch.device, model: nn.Module | CheckpointModel) -> InputError | None:
    return None


#: The torch engine's entry of the registry (:mod:`aerialmtl.inference.engines.names`): runs anything, anywhere.
SPEC = EngineSpec("torch", "torch", build_torch, _always_usable, over=torch_over, bf16_needs_amx=True,
                  takes_compile=True, layout="channels_last")

__all__ = ["SPEC", "TorchEngine", "build_torch", "compile_model", "torch_over"]
