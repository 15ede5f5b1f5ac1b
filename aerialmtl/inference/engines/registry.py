"""The engines by name: one :class:`EngineSpec` each in :data:`ENGINES`, shaped like the encoder registry
(:mod:`aerialmtl.models.encoders`).

Adding an engine is one module of its own (a class with the :class:`~aerialmtl.inference.engines.base.Engine`
members, a function that builds it from an :class:`~aerialmtl.inference.engines.base.EngineSetup`, and one that
says why it cannot run somewhere) and one entry here, nothing else: ``predict --engine`` and the QGIS dialog
offer the names of :data:`ENGINES` (read from here), and tests/test_engines.py predicts with a fake third engine
registered so. The order of :data:`ENGINES` is ``auto``'s preference: :func:`resolve_engine` (the one resolver of
``auto`` against the registry; :func:`~aerialmtl.inference.engine_choice.choose_engine` adds the measured table on
top of it) takes the first engine that can run the model on the device; an engine appended after
:data:`FALLBACK` (which runs anything, anywhere) is never picked by ``auto``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from aerialmtl.errors import InputError
from aerialmtl.inference.engines.base import Engine, EngineSetup
from aerialmtl.inference.engines.openvino_engine import build_openvino, openvino_unusable
from aerialmtl.inference.engines.torch_engine import build_torch, torch_over
from aerialmtl.inference.model_record import CheckpointModel


@dataclass(frozen=True)
class EngineSpec:
    """One engine of the registry.

    Attributes:
        name: the ``engine`` value that selects it (recorded in ``prediction.json``).
        label: how messages spell it (``OpenVINO``).
        build: setup → the engine.
        unusable: (device, model) → why the engine cannot run that model there (the error to raise), or ``None``.
        over: (model another engine prepared, setup) → the engine over that model, not compiled; what ``auto``'s
            fallback builds (needed of :data:`FALLBACK` only).
    """

    name: str
    label: str
    build: Callable[[EngineSetup], Engine]
    unusable: Callable[[torch.device, nn.Module | CheckpointModel], InputError | None]
    over: Callable[[nn.Module, EngineSetup], Engine] | None = None


def _always_usable(device: torch.device, model: nn.Module | CheckpointModel) -> InputError | None:
    return None


#: Name → engine, in ``auto``'s order of preference (the module docstring).
ENGINES: dict[str, EngineSpec] = {
    "openvino": EngineSpec("openvino", "OpenVINO", build_openvino, openvino_unusable),
    "torch": EngineSpec("torch", "torch", build_torch, _always_usable, over=torch_over),
}
#: The engine ``auto`` falls back to when the one it chose fails on the first batch (runs anything, anywhere).
FALLBACK = "torch"


def engine_spec(name: str) -> EngineSpec:
    """The registry entry of engine ``name``.

    Raises:
        InputError: no such engine (naming the ones there are).
    """
    if name not in ENGINES:
        raise InputError(f"‹engine={name}› is not supported; use auto, {' or '.join(ENGINES)}", param="engine")
    return ENGINES[name]


def resolve_engine(engine: str, device: torch.device, model: nn.Module | CheckpointModel) -> str:
    """``auto`` → the first engine of :data:`ENGINES` that can run ``model`` on ``device`` (``openvino`` on a CPU
    where it is installed and ``model`` is a D3-Net, else ``torch``); a named engine → itself, once it can run
    ``model`` on ``device``.

    Raises:
        InputError: an unknown engine, or one that cannot run here (its :attr:`EngineSpec.unusable` error).
    """
    if engine == "auto":
        return next((name for name, spec in ENGINES.items() if spec.unusable(device, model) is None), FALLBACK)
    why = engine_spec(engine).unusable(device, model)
    if why is not None:
        raise why
    return engine


def build_engine(setup: EngineSetup) -> Engine:
    """The engine ``setup.resolved.engine`` (already resolved by :func:`resolve_engine`) for ``setup.model``."""
    return engine_spec(setup.resolved.engine).build(setup)


def fallback_engine(failed: Engine, setup: EngineSetup) -> Engine:
    """The :data:`FALLBACK` engine over the model ``failed`` prepared (not compiled), for ``auto``'s fallback."""
    over = ENGINES[FALLBACK].over
    assert over is not None, "the fallback engine builds over another engine's model"
    return over(failed.model, setup)


__all__ = ["ENGINES", "FALLBACK", "EngineSpec", "build_engine", "engine_spec", "fallback_engine", "resolve_engine"]
