"""The engines' names: the one list, without importing any engine (so without torch).

:data:`ENGINE_MODULES` maps each engine's name to the module that defines it (its ``SPEC``, an
:class:`~aerialmtl.inference.engines.base.EngineSpec`), in ``auto``'s order of preference. The registry
(:data:`aerialmtl.inference.engines.registry.ENGINES`) reads its engines from here, and the command line its
``--engine`` choices (``--help`` and shell completion import no torch). Adding an engine is its module and one
entry here.
"""

from __future__ import annotations

#: Engine name → the module whose ``SPEC`` it is, in ``auto``'s order of preference.
ENGINE_MODULES: dict[str, str] = {
    "openvino": "aerialmtl.inference.engines.openvino_engine",
    "torch": "aerialmtl.inference.engines.torch_engine",
}
#: The engine ``auto`` falls back to when the one it chose fails on the first batch (runs anything, anywhere).
FALLBACK = "torch"

__all__ = ["ENGINE_MODULES", "FALLBACK"]
