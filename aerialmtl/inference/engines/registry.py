"""The engines by name: :data:`ENGINES`, one :class:`~aerialmtl.inference.engines.base.EngineSpec` each, shaped
like the encoder registry (:mod:`aerialmtl.models.encoders`).

The names and their order are :data:`~aerialmtl.inference.engines.names.ENGINE_MODULES` (a table that imports no
engine, so the command line reads it without torch); each engine's entry is its module's ``SPEC``, imported when
first asked for. Adding an engine is one module of its own (a class with the
:class:`~aerialmtl.inference.engines.base.Engine` members, a function that builds it from an
:class:`~aerialmtl.inference.engines.base.EngineSetup`, one that says why it cannot run somewhere, and its
``SPEC``) and one entry in that table, nothing else: ``predict --engine`` offers the names of the table, and
tests/test_engine_registry.py predicts with a fake third engine added so. ``auto`` weighs the engines by what
their specs declare (:func:`~aerialmtl.inference.engine_choice.auto_engine`); the order breaks ties.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping

import torch
from torch import nn

from aerialmtl.errors import InputError
from aerialmtl.inference.engines.base import Engine, EngineSetup, EngineSpec
from aerialmtl.inference.engines.names import ENGINE_MODULES, FALLBACK
from aerialmtl.inference.model_record import CheckpointModel


class _Registry(Mapping[str, EngineSpec]):
    """Name → :class:`EngineSpec`, read from :data:`~aerialmtl.inference.engines.names.ENGINE_MODULES`.

    The names in its order, each the ``SPEC`` of its module.
    """

    def __getitem__(self, name: str) -> EngineSpec:
        spec = importlib.import_module(ENGINE_MODULES[name]).SPEC
        if not isinstance(spec, EngineSpec) or spec.name != name:
            raise TypeError(f"{ENGINE_MODULES[name]}.SPEC must be the EngineSpec of engine {name!r}, got {spec!r}")
        return spec

    def __iter__(self) -> Iterator[str]:
        return iter(list(ENGINE_MODULES))

    def __len__(self) -> int:
        return len(ENGINE_MODULES)


#: Name → engine, in ``auto``'s order of preference (the module docstring).
ENGINES: Mapping[str, EngineSpec] = _Registry()


def engine_spec(name: str) -> EngineSpec:
    """The registry entry of engine ``name``.

    Raises:
        InputError: no such engine (naming the ones there are).
    """
    if name not in ENGINES:
        raise InputError(f"‹engine={name}› is not supported; use auto, {' or '.join(ENGINES)}", param="engine")
    return ENGINES[name]


def usable_engines(device: torch.device, model: nn.Module | CheckpointModel) -> list[EngineSpec]:
    """The engines that can run ``model`` on ``device``, in the registry's order (what ``auto`` chooses among:
    :func:`~aerialmtl.inference.engine_choice.auto_engine`).
    """
    return [spec for spec in ENGINES.values() if spec.unusable(device, model) is None]


def resolve_engine(engine: str, device: torch.device, model: nn.Module | CheckpointModel) -> str:
    """The engine named ``engine``, once it can run ``model`` on ``device`` (``auto`` is
    :func:`~aerialmtl.inference.engine_choice.choose_engine`'s).

    Raises:
        InputError: an unknown engine, or one that cannot run here (its :attr:`EngineSpec.unusable` error).
    """
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


__all__ = ["ENGINES", "FALLBACK", "EngineSpec", "build_engine", "engine_spec", "fallback_engine", "resolve_engine",
           "usable_engines"]
