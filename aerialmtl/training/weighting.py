"""Combining task losses into one training objective.

* :class:`EqualWeighting` — the paper's default: L = Σ_t w_t · L_t with fixed weights (all 1 unless
  configured).
* :class:`UncertaintyWeighting` — Kendall, Gal & Cipolla (CVPR 2018), homoscedastic task uncertainty
  with one learned log-variance s_t = log σ_t² per task:

  - regression task (Gaussian likelihood): ½·exp(−s_t)·L_t + ½·s_t   (= L_t/(2σ²) + log σ)
  - classification task (softmax with temperature σ², their approximation):
    exp(−s_t)·L_t + ½·s_t                                            (= L_t/σ² + log σ)

  ``height`` is a regression task, ``classes`` a classification task. s_t starts at 0 (σ = 1) and is
  learned jointly with the network: the training loop must give ``weighting.parameters()`` to the
  optimiser (no weight decay on them).

Both are modules with ``forward(losses: dict[str, Tensor]) -> Tensor`` and ``weights() -> dict[str, float]``
(the current effective multiplier of each task loss, for logging).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import nn

from aerialmtl.errors import ConfigError

#: Kendall et al.'s likelihood type of each task.
TASK_KIND = {"height": "regression", "classes": "classification"}


def _check_losses(tasks: Sequence[str], losses: Mapping[str, torch.Tensor]) -> None:
    missing = [t for t in tasks if t not in losses]
    if missing:
        raise KeyError(f"task weighting: no loss for task(s) {missing}; got losses for {sorted(losses)}")


class EqualWeighting(nn.Module):
    """L = Σ_t w_t · L_t with fixed weights.

    Args:
        tasks: task names.
        weights: optional ``{task: w_t}`` (missing tasks get 1.0).
    """

    def __init__(self, tasks: Sequence[str], weights: Mapping[str, float] | None = None) -> None:
        super().__init__()
        weights = dict(weights or {})
        unknown = [t for t in weights if t not in tasks]
        if unknown:
            raise ConfigError(f"task weights: unknown task(s) {unknown}; the model's tasks are {list(tasks)}")
        bad = {t: w for t, w in weights.items() if not w >= 0}
        if bad:
            raise ConfigError(f"task weights: must be ≥ 0, got {bad}")
        self.tasks = tuple(tasks)
        self._weights = {t: float(weights.get(t, 1.0)) for t in self.tasks}

    def forward(self, losses: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The fixed-weight sum of the task losses."""
        _check_losses(self.tasks, losses)
        total = self._weights[self.tasks[0]] * losses[self.tasks[0]]
        for t in self.tasks[1:]:
            total = total + self._weights[t] * losses[t]
        return total

    def weights(self) -> dict[str, float]:
        """Task → its weight."""
        return dict(self._weights)


class UncertaintyWeighting(nn.Module):
    """Learned homoscedastic-uncertainty weighting (Kendall et al. 2018), see the module docstring.

    Args:
        tasks: task names (``height`` → regression form, ``classes`` → classification form).
        init_log_var: initial s_t = log σ_t².
        kinds: optional override ``{task: "regression" | "classification"}``.

    Attributes:
        log_vars: ``nn.ParameterDict`` of scalar s_t.
    """

    def __init__(self, tasks: Sequence[str], init_log_var: float = 0.0,
                 kinds: Mapping[str, str] | None = None) -> None:
        super().__init__()
        self.tasks = tuple(tasks)
        kinds = {**TASK_KIND, **dict(kinds or {})}
        for t in self.tasks:
            if kinds.get(t) not in ("regression", "classification"):
                raise ConfigError(f"uncertainty weighting: task {t!r} needs a kind, 'regression' or "
                                  f"'classification', got {kinds.get(t)!r}")
        self.kinds = {t: kinds[t] for t in self.tasks}
        self.log_vars = nn.ParameterDict({t: nn.Parameter(torch.tensor(float(init_log_var))) for t in self.tasks})

    def _factor(self, task: str) -> float:
        return 0.5 if self.kinds[task] == "regression" else 1.0

    def forward(self, losses: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The uncertainty-weighted sum of the task losses (learned log-variances)."""
        _check_losses(self.tasks, losses)
        total = torch.zeros((), device=self.log_vars[self.tasks[0]].device)
        for t in self.tasks:
            s = self.log_vars[t]
            total = total + self._factor(t) * torch.exp(-s) * losses[t].float() + 0.5 * s
        return total

    def weights(self) -> dict[str, float]:
        """Task → its current effective weight."""
        return {t: self._factor(t) * float(torch.exp(-self.log_vars[t].detach())) for t in self.tasks}


WEIGHTINGS = {"equal": EqualWeighting, "uncertainty": UncertaintyWeighting}


def build_weighting(name: str, tasks: Sequence[str], **kwargs: object) -> nn.Module:
    """Build a weighting by name (``equal`` or ``uncertainty``); ``kwargs`` go to its constructor."""
    if name not in WEIGHTINGS:
        raise ConfigError(f"task weighting: got {name!r}; valid choices are {', '.join(WEIGHTINGS)}")
    result: nn.Module = WEIGHTINGS[name](tasks, **kwargs)
    return result


__all__ = ["EqualWeighting", "UncertaintyWeighting", "build_weighting", "WEIGHTINGS", "TASK_KIND"]
