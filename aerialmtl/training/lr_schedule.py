"""The learning rate of each optimisation step (``schedule.lr_schedule`` and ``schedule.warmup_steps``).

A pure function of the step number, so a resumed run follows exactly the schedule of an uninterrupted one
(nothing to save in ``last.pt``).
"""

from __future__ import annotations

import math
from typing import Literal


def lr_factor(step: int, total: int, kind: Literal["constant", "cosine"], warmup: int = 0) -> float:
    """Multiplier of ``optim.lr`` for the optimisation step that starts after ``step`` steps.

    Args:
        step: steps done before this one (0 for the first).
        total: the run's planned number of steps (the cosine reaches 0 there).
        kind: ``constant`` or ``cosine``.
        warmup: linear warm-up steps: the factor is ``(step + 1) / warmup`` for the first ``warmup`` steps.

    Returns:
        A factor in (0, 1]; the cosine's last step keeps a small positive rate (it never stops learning).
    """
    if step < warmup:
        return (step + 1) / warmup
    if kind == "constant":
        return 1.0
    span = max(1, total - warmup)
    t = min(step - warmup, span - 1) / span
    return 0.5 * (1.0 + math.cos(math.pi * t))


__all__ = ["lr_factor"]
