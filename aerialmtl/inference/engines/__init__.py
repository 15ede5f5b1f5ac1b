"""What runs the model in prediction: the ``torch`` engine or the ``openvino`` engine, behind one interface.

* ``torch`` — the model in PyTorch (eager, or ``torch.compile``); the only engine on CUDA.
* ``openvino`` — the same (loaded, BatchNorm-folded) model converted with ``openvino.convert_model``
  and compiled for the CPU, once per window shape. OpenVINO fuses DenseNet's many small concatenations
  and kernels that torch's eager mode runs one by one, and runs bf16 at the CPU's native speed
  (AVX-512-BF16 or AMX). How much faster is measured per kind of CPU in the shipped table
  (``aerialmtl/resources/engine_choice.yaml``, :mod:`~aerialmtl.inference.engine_choice`); on the Zen 4 CPU
  measured there (AVX-512-BF16, no AMX), OpenVINO bf16 ran the model alone about 3.5× torch fp32 and the whole
  prediction 1.14× (T = 1).

``auto`` (:func:`~aerialmtl.inference.engine_choice.auto_engine`) weighs the engines that can run the model on the
device by the measured table of the CPU's kind and, where it has none, by what each engine's spec declares
(:attr:`EngineSpec.speedup`), with a cold cache's compilation (:attr:`EngineSpec.compile_mpx`) against the job.

The package: :mod:`~aerialmtl.inference.engines.base` (the :class:`Engine` protocol, what an engine is built
from), :mod:`~aerialmtl.inference.engines.registry` (the engines by name, ``auto``, the fallback), one module
per engine (:mod:`~aerialmtl.inference.engines.torch_engine`, :mod:`~aerialmtl.inference.engines.openvino_engine`
with its graphs and requests beside it). Adding an engine is one module (with its ``SPEC``) and one entry in
:data:`~aerialmtl.inference.engines.names.ENGINE_MODULES`.

Both engines give the runner (:class:`~aerialmtl.inference.runner.ModelRunner`) per-window statistics
through the same code: T = 1 is one forward pass (height, softmax of the logits); T > 1 runs the encoder
once per window and the decoder T times, accumulated by
:func:`~aerialmtl.models.mc_dropout.accumulate_samples`. On the OpenVINO engine the dropout masks are
explicit inputs of the decoder, drawn by :func:`~aerialmtl.models.mc_dropout.dropout_masks` from the
same ``(seed, window, sample)`` keys as the torch path's seeded hooks: both engines sample the same
masks. The OpenVINO engine runs one window (and one sample) per infer request, so its results do not
depend on the batch size or the sample chunking either. Its forward graph (T = 1) and decoder graph (T > 1) hand
the class logits back channels last (:data:`FORWARD_CHANNELS_LAST`), as the convolution wrote them, and the
host's softmax and MC class kernel read them so.

Running: the model is compiled for ``streams`` parallel streams of ``threads / streams`` threads each
(:func:`aerialmtl.runtime.resolve_threads`: on 2 cores, two one-thread streams), with one infer request per
stream used in turn. :meth:`OpenVINOEngine.submit` starts a batch's windows and returns at once, so the
predictor blends and writes one batch while the next ones run; MC samples are started one chunk ahead of
their accumulation. Narrow streams keep a CPU shared with other processes busy: one wide stream splits each
layer over all its threads and waits for the slowest (bench/RESULTS.md, "predict end to end on CPUs").

Precision: fp32, or bf16 (``INFERENCE_PRECISION_HINT``) on a CPU with native bf16 under ``auto``
(:func:`aerialmtl.runtime.resolve_precision`); the statistics are accumulated in float32 either way.

Cache: converting the model takes seconds to a minute; the converted model (OpenVINO IR) and the compiled
models (one per window shape and precision) are kept in the ``openvino`` store, ``<store>/<fingerprint>``
(:mod:`aerialmtl.stores`: in the platform's cache folder; ``AERIALMTL_OPENVINO_CACHE`` moves it), keyed by a
fingerprint of the weights, the model configuration and the versions of aerialmtl and OpenVINO: a second run on the same
checkpoint loads both instead of paying again. A warm run imports the compiled model without reading the IR,
and does not load the torch model at all: the checkpoint's metadata, output names and dropout layers come from
its record beside the cache (:mod:`aerialmtl.inference.model_record`). Every entry carries its checksum and is
written whole (:mod:`aerialmtl.inference.engine_cache`): a corrupt or non-regular entry is rebuilt with a
warning, and a folder (or temporary folder) that cannot be written means a prediction without caching (one
warning naming it), never a failed one.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from aerialmtl.inference.engines.base import Done, Engine, EngineSetup, EngineSpec, Pending
    from aerialmtl.inference.engines.names import ENGINE_MODULES, FALLBACK
    from aerialmtl.inference.engines.openvino_engine import OPENVINO_INSTALL, OpenVINOEngine, openvino_available
    from aerialmtl.inference.engines.openvino_graphs import CONVERT_SIZE, cache_root, fingerprint
    from aerialmtl.inference.engines.registry import (
        ENGINES,
        build_engine,
        engine_spec,
        fallback_engine,
        resolve_engine,
        usable_engines,
    )
    from aerialmtl.inference.engines.torch_engine import TorchEngine, compile_model

#: Where each name of the package lives: imported on first use, so that :mod:`~aerialmtl.inference.engines.names`
#: (what the command line reads for ``--engine``) loads without torch.
_WHERE = {
    **dict.fromkeys(("Done", "Engine", "EngineSetup", "EngineSpec", "Pending"), "base"),
    **dict.fromkeys(("ENGINE_MODULES", "FALLBACK"), "names"),
    **dict.fromkeys(("OPENVINO_INSTALL", "OpenVINOEngine", "openvino_available"), "openvino_engine"),
    **dict.fromkeys(("CONVERT_SIZE", "cache_root", "fingerprint"), "openvino_graphs"),
    **dict.fromkeys(("ENGINES", "build_engine", "engine_spec", "fallback_engine", "resolve_engine", "usable_engines"),
                    "registry"),
    **dict.fromkeys(("TorchEngine", "compile_model"), "torch_engine"),
}


def __getattr__(name: str) -> Any:
    """The package's names, each imported from its module on first use (:data:`_WHERE`)."""
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


__all__ = ["CONVERT_SIZE", "ENGINES", "ENGINE_MODULES", "FALLBACK", "OPENVINO_INSTALL", "Done", "Engine", "EngineSetup",
           "EngineSpec", "OpenVINOEngine", "Pending", "TorchEngine", "build_engine", "cache_root", "compile_model",
           "engine_spec", "fallback_engine", "fingerprint", "openvino_available", "resolve_engine", "usable_engines"]
