"""An exponential moving average of the weights (``optim.ema``), swapped into the model where it is used.

:class:`WeightAverage` keeps a shadow copy of the model's ``state_dict`` (parameters and BatchNorm buffers):
after every optimisation step each floating-point tensor moves ``1 − decay`` of the way to the model's
(``shadow ← decay · shadow + (1 − decay) · weights``); integer buffers (BatchNorm's batch counters) are
copied. The trainer validates and writes checkpoints with the average in the model
(:meth:`WeightAverage.applied`) and trains the raw weights between.

Why: the last steps of a short training move the weights back and forth by amounts that depend on float
rounding (another CPU kind or thread count sums in another order); the average over the last ~1/(1 − decay)
steps is a far more stable model than any single step's (bench/RESULTS.md, "the demo across CPU kinds").
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn


class WeightAverage:
    """The moving average of ``model``'s weights; starts equal to them.

    Args:
        model: the model being trained (its ``state_dict`` keys and shapes define the average's).
        decay: in (0, 1); the average's horizon is about ``1 / (1 − decay)`` steps.
    """

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.shadow: dict[str, torch.Tensor] = {k: v.detach().clone() for k, v in model.state_dict().items()}

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the average towards ``model``'s current weights (call after each optimiser step)."""
        current = model.state_dict()
        floats = [k for k, v in self.shadow.items() if v.is_floating_point()]
        if floats:
            torch._foreach_lerp_([self.shadow[k] for k in floats], [current[k].detach() for k in floats],
                                 1.0 - self.decay)
        for k, v in self.shadow.items():
            if not v.is_floating_point():
                v.copy_(current[k])

    @contextlib.contextmanager
    def applied(self, model: nn.Module) -> Iterator[dict[str, torch.Tensor]]:
        """Inside the block ``model`` holds the average; its raw weights (yielded, a copy) come back after."""
        raw = {k: v.detach().clone() for k, v in model.state_dict().items()}
        model.load_state_dict(self.shadow)
        try:
            yield raw
        finally:
            model.load_state_dict(raw)

    def load(self, averaged: dict[str, torch.Tensor]) -> None:
        """Continue from a saved average (a checkpoint's weights) instead of the model's current weights."""
        for k, v in self.shadow.items():
            v.copy_(averaged[k])


__all__ = ["WeightAverage"]
