"""The engines' names: the one list, without importing any engine (so without torch).

The package imports its modules on first use (:mod:`aerialmtl.inference.engines`), so this one loads light.

:data:`ENGINE_MODULES` maps each engine's name to the module that defines it (its ``SPEC``, an
:class:`~aerialmtl.inference.engines.base.EngineSpec`), in the order that breaks ``auto``'s ties
(:func:`~aerialmtl.inference.engine_choice.auto_engine`). The registry
(:data:`aerialmtl.inference.engines.registry.ENGINES`) reads its engines from here, and the command line its
``--engine`` choices (``--help`` and shell completion import no torch). Adding an engine is its module and one
entry here.
"""

from __future__ import annotations

#: Engine name → the module whose ``SPEC`` it is; the first wins ``auto``'s ties.
ENGINE_MODULES: dict[str, str] = {
    "openvino": "aerialmtl.inference.engines.openvino_engine",
    "torch": "aerialmtl.inference.engines.torch_engine",
}
#: The engine ``auto`` falls back to when the one it chose fails on the first batch (runs anything, anywhere).
FALLBACK = "torch"

__all__ = ["ENGINE_MODULES", "FALLBACK"]
