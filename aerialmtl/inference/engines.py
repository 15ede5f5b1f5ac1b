"""What runs the model in prediction: the ``torch`` engine or the ``openvino`` engine, behind one interface.

* ``torch`` — the model in PyTorch (eager, or ``torch.compile``); the only engine on CUDA.
* ``openvino`` — the same (loaded, BatchNorm-folded) model converted with ``openvino.convert_model``
  and compiled for the CPU, once per window shape. OpenVINO fuses DenseNet's many small concatenations
  and kernels that torch's eager mode runs one by one, and runs bf16 at the CPU's native speed
  (AVX-512-BF16 or AMX): on a Zen 4 CPU (AVX-512-BF16, no AMX) 1.6× torch fp32 for the model alone and
  2× end to end at T = 8 (bench/RESULTS.md, CPU engines); more on CPUs with AMX.

``auto`` (:func:`resolve_engine`) is ``openvino`` on a CPU when OpenVINO is installed and the model is a
D3-Net (``encode``/``decode``), ``torch`` otherwise.

Both engines give the runner (:class:`~aerialmtl.inference.runner.ModelRunner`) per-window statistics
through the same code: T = 1 is one forward pass (height, softmax of the logits); T > 1 runs the encoder
once per window and the decoder T times, accumulated by
:func:`~aerialmtl.models.mc_dropout.accumulate_samples`. On the OpenVINO engine the dropout masks are
explicit inputs of the decoder, drawn by :func:`~aerialmtl.models.mc_dropout.dropout_masks` from the
same ``(seed, window, sample)`` keys as the torch path's seeded hooks: both engines sample the same
masks. The OpenVINO engine runs one window (and one sample) per call, so its results do not depend on the
batch size or the sample chunking either.

Precision: fp32, or bf16 (``INFERENCE_PRECISION_HINT``) on a CPU with native bf16 under ``auto``
(:func:`aerialmtl.runtime.resolve_precision`); the statistics are accumulated in float32 either way.

Cache: converting the model takes seconds to a minute; the converted model (OpenVINO IR) and the compiled
models (one per window shape and precision) are kept under ``$XDG_CACHE_HOME/aerialmtl/openvino/<fingerprint>``
(default ``~/.cache``; ``AERIALMTL_OPENVINO_CACHE`` overrides the root), keyed by a fingerprint of the
weights, the model configuration and the versions of aerialmtl and OpenVINO: a second run on the same
checkpoint loads both instead of paying again. Every entry carries its checksum and is written whole
(:mod:`aerialmtl.inference.engine_cache`): a corrupt entry is rebuilt with a warning, and a folder that
cannot be written means a prediction without caching (one warning naming it), never a failed one.
"""

from __future__ import annotations

import hashlib
import io
import os
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
import torch
from torch import nn

from aerialmtl._version import __version__
from aerialmtl.errors import InputError
from aerialmtl.inference.engine_cache import EngineCache
from aerialmtl.models.mc_dropout import (
    _SEEDABLE,
    DropoutSite,
    McStatistics,
    accumulate_samples,
    dropout_masks,
    dropout_sites,
    single_pass_statistics,
)

if TYPE_CHECKING:
    import openvino

EngineName = Literal["auto", "torch", "openvino"]
#: The command that installs the OpenVINO engine (named in the error when it is missing).
OPENVINO_INSTALL = "pip install openvino"
#: Side of the example input the model is converted with (any multiple of 32; small converts fast).
CONVERT_SIZE = 64


class Engine(Protocol):
    """What runs the model in prediction: the one interface of the ``torch`` engine
    (:class:`~aerialmtl.inference.runner.TorchEngine`) and the ``openvino`` engine (:class:`OpenVINOEngine`).

    A new engine implements these two members; :func:`resolve_engine` and the runner
    (:class:`~aerialmtl.inference.runner.ModelRunner`) choose and build it.
    """

    #: ``"torch"`` or ``"openvino"`` (recorded in ``prediction.json``).
    name: str

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        """Statistics of each window of a normalised batch.

        Args:
            x: (B, C, h, w) normalised windows, on the engine's device.
            keys: one dropout-mask key per window (masks depend on the window, not on the batch).
            samples: MC-dropout samples T (1: one deterministic pass).
            seed: the run's seed of the dropout masks.
            sample_batch: MC samples decoded per call (bounds memory, not results).

        Returns:
            per-window height mean/std (B, h, w, metres), class probabilities (B, h, w, K) and mean
            per-sample entropy, as :class:`~aerialmtl.models.mc_dropout.McStatistics`.
        """
        ...


def openvino_available() -> bool:
    """Whether ``import openvino`` works."""
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False
    return True


def _convertible(model: nn.Module) -> bool:
    from aerialmtl.models.d3net import D3Net

    return isinstance(model, D3Net)


def resolve_engine(engine: str, device: torch.device, model: nn.Module) -> Literal["torch", "openvino"]:
    """``auto`` → ``openvino`` on a CPU when it is installed and ``model`` is a D3-Net, else ``torch``.

    Raises:
        InputError: an unknown engine; ``openvino`` on CUDA, for another model, or not installed (one line
            naming :data:`OPENVINO_INSTALL`).
    """
    if engine == "auto":
        ok = device.type == "cpu" and _convertible(model) and openvino_available()
        return "openvino" if ok else "torch"
    if engine == "torch":
        return "torch"
    if engine != "openvino":
        raise InputError(f"‹engine={engine}› is not supported; use auto, torch or openvino", param="engine")
    if device.type != "cpu":
        raise InputError(f"‹engine=openvino› runs on the CPU, not on {device}; pass ‹device=cpu› or ‹engine=torch›",
                         param="engine")
    if not _convertible(model):
        raise InputError(f"‹engine=openvino› converts D3-Net models only, not {type(model).__name__}; "
                         "pass ‹engine=torch›", param="engine")
    if not openvino_available():
        raise InputError(f"‹engine=openvino› needs OpenVINO, which is not installed; install it with "
                         f"`{OPENVINO_INSTALL}` or pass ‹engine=torch›")
    return "openvino"


def cache_root() -> Path:
    """Root of the OpenVINO caches (see the module docstring)."""
    if os.environ.get("AERIALMTL_OPENVINO_CACHE"):
        return Path(os.environ["AERIALMTL_OPENVINO_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "aerialmtl" / "openvino"


def fingerprint(model: nn.Module, extra: str = "") -> str:
    """A hash of the weights and buffers of ``model``, its class and ``extra`` (configuration, versions)."""
    h = hashlib.blake2b(digest_size=12)
    h.update(f"{type(model).__module__}.{type(model).__qualname__}|{extra}".encode())
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        if t.numel():
            h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()


# ---- modules traced for OpenVINO --------------------------------------------------------------------
class _MaskMul(nn.Module):
    """A dropout layer whose mask is an input: ``x · mask`` (mask set by :class:`_Decoder` per call)."""

    def __init__(self) -> None:
        super().__init__()
        self.mask: torch.Tensor | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        assert self.mask is not None
        return x * self.mask


def model_outputs(model: nn.Module, tasks: Sequence[str]) -> tuple[str, ...]:
    """The keys of ``model``'s output dict in order: its ``outputs`` (a D3-Net: the tasks, plus
    ``height_scale`` for an aleatoric head), else ``tasks``.
    """
    return tuple(getattr(model, "outputs", None) or tasks)


class _Forward(nn.Module):
    def __init__(self, model: nn.Module, tasks: Sequence[str]) -> None:
        super().__init__()
        self.model, self.tasks = model, model_outputs(model, tasks)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(x)
        return tuple(out[t] for t in self.tasks)


class _Encoder(nn.Module):
    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.model.encode(x))  # type: ignore[operator]


class _Decoder(nn.Module):
    """``decode`` with the seedable dropout layers replaced by :class:`_MaskMul` (masks as inputs)."""

    def __init__(self, model: nn.Module, tasks: Sequence[str], n_feats: int) -> None:
        super().__init__()
        import copy

        self.model = copy.deepcopy(model).eval()
        self.tasks, self.n_feats = model_outputs(model, tasks), n_feats
        self.sites: list[_MaskMul] = []
        for parent in list(self.model.modules()):
            for name, child in list(parent.named_children()):
                if isinstance(child, _SEEDABLE) and float(child.p) > 0:
                    mul = _MaskMul()
                    setattr(parent, name, mul)
                    self.sites.append(mul)

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        feats, masks = list(inputs[:self.n_feats]), inputs[self.n_feats:]
        for site, mask in zip(self.sites, masks):
            site.mask = mask
        out = self.model.decode(feats)  # type: ignore[operator]
        return tuple(out[t] for t in self.tasks)


# ---- engines ----------------------------------------------------------------------------------------
class OpenVINOEngine:
    """The model compiled by OpenVINO for the CPU (see the module docstring).

    Args:
        model: the prepared (BatchNorm-folded, eval) D3-Net.
        in_channels: its input bands.
        tasks: its tasks, in output order.
        precision: ``"bf16"`` or ``"fp32"``.
        cache_dir: where the IR and compiled models go (default :func:`cache_root`/fingerprint; nothing is
            cached with ``cache=False``; :class:`~aerialmtl.inference.engine_cache.EngineCache`).
        cache: keep converted and compiled models on disk.
    """

    name = "openvino"

    def __init__(self, model: nn.Module, in_channels: int, tasks: Sequence[str], precision: str,
                 cache_dir: str | Path | None = None, cache: bool = True) -> None:
        import openvino as ov

        self.ov = ov
        self.model = model
        self.in_channels = in_channels
        self.tasks = model_outputs(model, tasks)  # output order of the converted graphs
        self.precision = precision
        self._sites: list[DropoutSite] | None = None
        self.core = ov.Core()
        self.cache_dir: Path | None = None
        if cache:
            cfg = getattr(model, "cfg", "")
            extra = f"{__version__}|{ov.__version__}|{in_channels}|{self.tasks}|{cfg}|{CONVERT_SIZE}"
            self.cache_dir = Path(cache_dir) if cache_dir is not None else cache_root() / fingerprint(model, extra)
        self.cache = EngineCache(self.cache_dir)
        self._models: dict[str, openvino.Model] = {}
        self._compiled: dict[tuple[str, int, int], Any] = {}
        self._lock = threading.Lock()

    @property
    def sites(self) -> list[DropoutSite]:
        """The decoder's dropout layers (found on first use: only MC dropout needs them)."""
        if self._sites is None:
            self._sites = dropout_sites(self.model, self.in_channels)
        return self._sites

    # ---- conversion and compilation ---------------------------------------------------------------
    def _module(self, part: str) -> tuple[nn.Module, tuple[torch.Tensor, ...]]:
        s = CONVERT_SIZE
        x = torch.zeros((1, self.in_channels, s, s))
        if part == "forward":
            return _Forward(self.model, self.tasks), (x,)
        if part == "encode":
            return _Encoder(self.model), (x,)
        with torch.no_grad():
            feats = self.model.encode(x)  # type: ignore[operator]
        masks = [torch.ones((1, *site.shape(s, s))) for site in self.sites]
        return _Decoder(self.model, self.tasks, len(feats)), (*feats, *masks)

    def _ov_model(self, part: str) -> openvino.Model:
        if part in self._models:
            return self._models[part]
        cached = self.cache.read(f"{part}.ir")
        if cached is not None and len(cached) == 2:
            xml, weights = cached
            model = self.core.read_model(xml, self.ov.Tensor(np.frombuffer(weights, np.uint8).copy()))
        else:
            module, example = self._module(part)
            # Traced with autograd on: D3-Net's dense blocks then concatenate (which OpenVINO fuses)
            # instead of writing into one buffer in place, and a small example input traces fast.
            with torch.enable_grad(), warnings.catch_warnings():
                # shape checks traced as constants
                warnings.simplefilter("ignore", torch.jit.TracerWarning)  # type: ignore[attr-defined]
                traced = torch.jit.trace(module.eval(), example, check_trace=False, strict=False)
            model = self.ov.convert_model(traced)
            if self.cache.enabled:
                self.cache.write(f"{part}.ir", self._serialize(model))
        self._models[part] = model
        return model

    def _request(self, part: str, h: int, w: int) -> Any:
        key = (part, h, w)
        with self._lock:
            if key not in self._compiled:
                model = self._ov_model(part).clone()
                shapes: dict[int, list[int]] = {0: [1, self.in_channels, h, w]}
                if part == "decode":
                    feats = self._feature_shapes(h, w)
                    shapes = {k: list(s) for k, s in enumerate(feats)}
                    shapes.update({len(feats) + k: [1, *site.shape(h, w)] for k, site in enumerate(self.sites)})
                model.reshape(shapes)
                hint = "bf16" if self.precision == "bf16" else "f32"
                # as many threads as torch uses (torchrun's OMP_NUM_THREADS, torch.set_num_threads)
                config = {"INFERENCE_PRECISION_HINT": hint, "PERFORMANCE_HINT": "LATENCY",
                          "INFERENCE_NUM_THREADS": torch.get_num_threads()}
                compiled = self._compile(model, f"{part}.{h}x{w}.{hint}.blob", config)
                self._compiled[key] = compiled.create_infer_request()
            return self._compiled[key]

    def _serialize(self, model: openvino.Model) -> list[bytes]:
        """An IR's XML and weights as bytes (through a private temporary folder: OpenVINO writes files)."""
        import tempfile

        with tempfile.TemporaryDirectory(prefix="aerialmtl-ov-") as tmp:
            xml = Path(tmp) / "model.xml"
            self.ov.save_model(model, str(xml), compress_to_fp16=False)
            return [xml.read_bytes(), xml.with_suffix(".bin").read_bytes()]

    def _compile(self, model: openvino.Model, name: str, config: dict[str, Any]) -> Any:
        """``model`` compiled for the CPU: imported from cache entry ``name`` when it is there and whole,
        else compiled (and stored).
        """
        cached = self.cache.read(name)
        if cached is not None and len(cached) == 1:
            try:
                return self.core.import_model(io.BytesIO(cached[0]), "CPU", config)
            except RuntimeError as exc:  # a whole entry OpenVINO still refuses (e.g. written by another build)
                warnings.warn(f"cached OpenVINO model '{self.cache.folder}/{name}' could not be loaded "
                              f"({' '.join(str(exc).split())[:120]}); rebuilding it", UserWarning, stacklevel=2)
        compiled = self.core.compile_model(model, "CPU", config)
        if self.cache.enabled:
            self.cache.write(name, [compiled.export_model().getvalue()])
        return compiled

    def _feature_shapes(self, h: int, w: int) -> list[tuple[int, ...]]:
        enc = self._ov_model("encode")
        model = enc.clone()
        model.reshape({0: [1, self.in_channels, h, w]})
        return [tuple(o.get_shape()) for o in model.outputs]

    # ---- running ----------------------------------------------------------------------------------
    @staticmethod
    def _outputs(request: Any) -> list[torch.Tensor]:
        return [torch.from_numpy(np.array(request.get_output_tensor(k).data, copy=True))
                for k in range(len(request.model_outputs))]

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, C, h, w) normalised → ``{task: (B, C_t, h, w)}`` (float32, one window per call)."""
        h, w = x.shape[-2:]
        req = self._request("forward", h, w)
        outs: list[list[torch.Tensor]] = [[] for _ in self.tasks]
        for n in range(x.shape[0]):
            req.infer({0: x[n:n + 1].contiguous().numpy()})
            for k, t in enumerate(self._outputs(req)):
                outs[k].append(t)
        return {task: torch.cat(o) for task, o in zip(self.tasks, outs)}

    def encode(self, x: torch.Tensor) -> list[np.ndarray]:
        """(1, C, h, w) normalised → the encoder features (numpy, for :meth:`decode`)."""
        req = self._request("encode", *x.shape[-2:])
        req.infer({0: x.contiguous().numpy()})
        return [np.array(req.get_output_tensor(k).data, copy=True) for k in range(len(req.model_outputs))]

    def decode(self, feats: list[np.ndarray], masks: list[torch.Tensor], h: int, w: int) -> list[torch.Tensor]:
        """One image's features and one sample's masks → its outputs, in task order."""
        req = self._request("decode", h, w)
        inputs: dict[int, np.ndarray] = dict(enumerate(feats))
        inputs.update({len(feats) + k: m.numpy() for k, m in enumerate(masks)})
        req.infer(inputs)
        return self._outputs(req)

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        """Normalised (B, C, h, w) batch → statistics of each window (as the torch path)."""
        x = x.float()
        if samples == 1:
            return single_pass_statistics(self.forward(x))
        b, _, h, w = x.shape
        feats = [self.encode(x[n:n + 1]) for n in range(b)]

        def decode_chunk(done: int, s: int) -> dict[str, torch.Tensor]:
            outs: list[list[torch.Tensor]] = [[] for _ in self.tasks]
            for t in range(done, done + s):
                for n, key in enumerate(keys):
                    for k, o in enumerate(self.decode(feats[n], dropout_masks(self.sites, h, w, seed, key, t), h, w)):
                        outs[k].append(o)
            return {task: torch.cat(o) for task, o in zip(self.tasks, outs)}

        return accumulate_samples(decode_chunk, samples, max(1, sample_batch), b)


__all__ = ["CONVERT_SIZE", "Engine", "EngineName", "OPENVINO_INSTALL", "OpenVINOEngine", "cache_root", "fingerprint",
           "openvino_available", "resolve_engine"]
