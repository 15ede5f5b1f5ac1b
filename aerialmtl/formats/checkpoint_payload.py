"""What a checkpoint's payload may hold before anything uses it: a bounded number of values once shared references
are expanded (:func:`expanded_values`: a pickle bomb is refused before any walk of it), and weights that are a
mapping of finite tensors with no negative BatchNorm variance (:func:`check_state`).

:func:`aerialmtl.formats.checkpoint.read_checkpoint` applies them to every checkpoint it reads; training checks its
own weights and optimizer state with :func:`first_nonfinite` before writing one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from aerialmtl.errors import CheckpointError


def first_nonfinite(tensors: Any) -> str | None:
    """The name of the first floating-point tensor of mapping ``tensors`` holding NaN or ±inf, else ``None``.

    Nested mappings and lists (an optimizer's state) are searched too; names are joined with dots.
    """
    if isinstance(tensors, torch.Tensor):
        bad = tensors.is_floating_point() and tensors.numel() > 0 and not bool(torch.isfinite(tensors).all())
        return "" if bad else None
    items: Any = tensors.items() if isinstance(tensors, dict) else enumerate(tensors) \
        if isinstance(tensors, (list, tuple)) else ()
    for key, value in items:
        found = first_nonfinite(value)
        if found is not None:
            return f"{key}.{found}" if found else str(key)
    return None


#: Values (containers, scalars, tensors) a checkpoint's payload may hold once shared references are expanded: the
#: paper's DenseNet-121 with its Adam state holds about 5,400 (a tensor is one). A pickle can refer to one list
#: many times, so a 4 KB file can stand for 10²⁴ values: torch builds it in no time (shared), but any walk of it
#: (validation, a copy) would run out of memory or time. Such a payload is refused before anything walks it.
MAX_CHECKPOINT_VALUES = 5_000_000


def expanded_values(obj: Any, limit: int = MAX_CHECKPOINT_VALUES) -> int:
    """The values of ``obj`` (dicts, lists, tuples, sets and what they hold) counted as a walk of the tree would.

    Shared references are counted each time they are met (``limit + 1`` stands for "more", and for a structure
    that contains itself). Linear in the distinct objects: the count of each is kept.
    """
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    todo: list[tuple[Any, bool]] = [(obj, False)]
    keep: list[Any] = []  # the objects whose ids are keys, alive until the end (ids are not reused meanwhile)

    def parts(x: Any) -> list[Any]:
        if isinstance(x, dict):
            return [v for pair in x.items() for v in pair]
        if isinstance(x, (list, tuple, set, frozenset)):
            return list(x)
        return []

    while todo:
        x, done = todo.pop()
        key = id(x)
        if done:
            total = 1 + sum(sizes.get(id(c), 1) for c in parts(x))
            sizes[key] = min(total, limit + 1)
            on_path.discard(key)
            continue
        if key in sizes:
            continue
        inner = parts(x)
        if not inner:
            sizes[key] = 1
            keep.append(x)
            continue
        if key in on_path:
            return limit + 1
        on_path.add(key)
        keep.append(x)
        todo.append((x, True))
        for c in inner:
            if id(c) in on_path:
                return limit + 1
            if id(c) not in sizes:
                todo.append((c, False))
    return sizes[id(obj)]


def check_state(path: str | Path, state: Any) -> None:
    """Refuse the ``state_dict`` of checkpoint ``path`` unless it is a mapping of tensors, all finite, with no
    negative BatchNorm variance.

    Raises:
        CheckpointError: naming ``path``, the tensor and what to do.
    """
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(
            f"checkpoint '{path}' holds no valid state_dict (a mapping of weight tensors); use the best.pt or "
            "last.pt of one `aerialmtl train` run"
        )
    bad = first_nonfinite(state)
    if bad is not None:
        raise CheckpointError(
            f"checkpoint '{path}' holds NaN or inf weights ('{bad}'): the run that wrote it had diverged and its "
            "results would be garbage; use an earlier checkpoint, or retrain with a lower optim.lr"
        )
    negative = next((k for k, v in state.items() if k.endswith("running_var") and v.is_floating_point()
                     and v.numel() > 0 and bool((v < 0).any())), None)
    if negative is not None:  # no training writes one; engines disagree on it (NaN in torch, finite in OpenVINO)
        raise CheckpointError(
            f"checkpoint '{path}' holds a negative BatchNorm variance ('{negative}'), which no training writes: the "
            "file was edited or damaged and its results would be garbage; use another checkpoint (an earlier "
            "best.pt / last.pt)"
        )


__all__ = ["MAX_CHECKPOINT_VALUES", "check_state", "expanded_values", "first_nonfinite"]
