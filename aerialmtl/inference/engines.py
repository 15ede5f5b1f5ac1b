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
models (one per window shape and precision) are kept under ``$XDG_CACHE_HOME/aerialmtl/openvino/<fingerprint>``
(default ``~/.cache``; ``AERIALMTL_OPENVINO_CACHE`` overrides the root), keyed by a fingerprint of the
weights, the model configuration and the versions of aerialmtl and OpenVINO: a second run on the same
checkpoint loads both instead of paying again. A warm run imports the compiled model without reading the IR,
and does not load the torch model at all: the checkpoint's metadata, output names and dropout layers come from
its record beside the cache (:mod:`aerialmtl.inference.model_record`). Every entry carries its checksum and is
written whole (:mod:`aerialmtl.inference.engine_cache`): a corrupt entry is rebuilt with a warning, and a folder
that cannot be written means a prediction without caching (one warning naming it), never a failed one.
"""

from __future__ import annotations

import hashlib
import os
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, cast

import numpy as np
import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl._version import __version__
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.engine_cache import EngineCache
from aerialmtl.inference.model_record import CheckpointModel, resolve_model
from aerialmtl.models.d3net import inference_model
from aerialmtl.models.mc_dropout import (
    _SEEDABLE,
    DropoutSite,
    McStatistics,
    accumulate_samples,
    dropout_masks,
    dropout_sites,
    mc_statistics,
    single_pass_statistics,
)
from aerialmtl.runtime import CpuThreads, resolve_threads

if TYPE_CHECKING:
    import openvino

EngineName = Literal["auto", "torch", "openvino"]
#: The engines, by name: the one list (``auto`` picks one of them, :func:`resolve_engine`; :func:`build_engine`
#: builds it; ``predict --engine`` offers them).
ENGINES: tuple[str, ...] = ("torch", "openvino")
#: The command that installs the OpenVINO engine (named in the error when it is missing).
OPENVINO_INSTALL = "pip install openvino"
#: Side of the example input the model is converted with (any multiple of 32; small converts fast).
CONVERT_SIZE = 64
#: Outputs of the forward graph (T = 1) that leave it channels last, ``(1, h, w, C)``, instead of ``(1, C, h, w)``:
#: the host's softmax wants the classes of a pixel side by side, and OpenVINO's convolutions store them so (class
#: planes cost a reorder there and a transposing copy on the host: 0.84× the CPU of predict at T = 1, 8192², on
#: the near-null D3-Net of ``bench/predict.py`` with trained-like head biases; bench/RESULTS.md, issue 27). The
#: decoder graph (T > 1) does the same: the CPU's MC class kernel (:mod:`aerialmtl.models.class_kernel`) turns a
#: row into class planes in the cache, where OpenVINO's reorder to planes cost up to 75 ms per 1024² sample. The
#: engine hands them on as views in the models' ``(B, C, h, w)`` order (:func:`_as_planes`).
FORWARD_CHANNELS_LAST = ("classes",)
#: Version of the converted graphs' outputs (part of the cache key: a cache of other outputs is never read).
GRAPH_OUTPUTS = "forward-decoder-classes-nhwc"


class Engine(Protocol):
    """What runs the model in prediction: the one interface of the ``torch`` engine (:class:`TorchEngine`)
    and the ``openvino`` engine (:class:`OpenVINOEngine`).

    A new engine implements these members, is named in :data:`ENGINES`, and is chosen by
    :func:`resolve_engine` and built by :func:`build_engine` (the runner,
    :class:`~aerialmtl.inference.runner.ModelRunner`, calls both).
    """

    #: ``"torch"`` or ``"openvino"`` (recorded in ``prediction.json``).
    name: str

    @property
    def model(self) -> nn.Module:
        """The engine's own copy of the model, prepared for prediction (the fallback and the tests use it)."""
        ...

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

    def submit(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
               sample_batch: int) -> Pending:
        """Start :meth:`statistics` of a batch; ``.result()`` of the returned :class:`Pending` gives them (an
        engine that runs synchronously returns them computed, as :class:`Done`).
        """
        ...


def openvino_available() -> bool:
    """Whether ``import openvino`` works (:func:`aerialmtl.runtime.import_openvino`)."""
    try:
        runtime.import_openvino()
    except ImportError:
        return False
    return True


def _convertible(model: nn.Module | CheckpointModel) -> bool:
    from aerialmtl.models.d3net import D3Net

    return isinstance(model, (D3Net, CheckpointModel))  # a checkpoint's model is a D3-Net


def resolve_engine(engine: str, device: torch.device,
                   model: nn.Module | CheckpointModel) -> Literal["torch", "openvino"]:
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
    if engine not in ENGINES:
        raise InputError(f"‹engine={engine}› is not supported; use auto, {' or '.join(ENGINES)}", param="engine")
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


class _Compiled(nn.Module):
    """``torch.compile`` of the deterministic parts (``forward`` for T = 1, ``encode`` for MC) with the
    fallback of :class:`aerialmtl.runtime.CompileFallback`.

    The decoder stays eager under MC dropout: its per-window seeded masks are drawn by Python hooks.
    """

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model
        self._compiled = runtime.CompileFallback(model, "the model")

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        return cast(list[torch.Tensor], self._compiled("encode", x))

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        decode: Callable[[list[torch.Tensor]], dict[str, torch.Tensor]] = getattr(self.model, "decode")  # noqa: B009
        return decode(feats)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return cast(dict[str, torch.Tensor], self._compiled("forward", x))


def compile_model(model: nn.Module) -> nn.Module:
    """The model with ``torch.compile`` applied where it can be (see :class:`_Compiled`)."""
    return _Compiled(model)


class TorchEngine:
    """The model in PyTorch (eager, or ``torch.compile``), on any device: today's path and CUDA's only one.

    Args:
        net: the prepared model (:func:`~aerialmtl.models.d3net.inference_model`), or its compiled wrapper
            (:func:`compile_model`).
        model: the prepared model itself (its modes are switched for MC dropout).
        device, precision: where and how it runs (bf16 = autocast).
        tasks: the model's tasks.
    """

    name = "torch"

    def __init__(self, net: nn.Module, model: nn.Module, device: torch.device, precision: str,
                 tasks: Sequence[str]) -> None:
        self.net, self.model, self.device, self.precision, self.tasks = net, model, device, precision, tuple(tasks)

    def submit(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int, sample_batch: int) -> Pending:
        """:meth:`statistics`, computed now (torch runs synchronously)."""
        return Done(self.statistics(x, keys, samples, seed, sample_batch))

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        """Normalised (B, C, h, w) batch → statistics of each window (see :class:`McStatistics`)."""
        with torch.inference_mode(), runtime.autocast(self.device, self.precision):
            if samples == 1:
                self.model.eval()
                return single_pass_statistics(self.net(x))
            return mc_statistics(self.net, x, samples, sample_batch=sample_batch, seed=seed, keys=keys)


def build_engine(engine: Literal["torch", "openvino"], model: nn.Module | CheckpointModel, meta: ModelMeta,
                 device: torch.device, precision: str, *, compile: bool = False, threads: CpuThreads | None = None,
                 weights_key: str | None = None) -> Engine:
    """The engine named ``engine`` (:data:`ENGINES`, already resolved by :func:`resolve_engine`) for ``model``.

    Args:
        model: the loaded model (each engine prepares its own copy: folded BatchNorms, channels-last), or a
            :class:`~aerialmtl.inference.model_record.CheckpointModel` (the OpenVINO engine loads it only when
            its cache lacks an entry; the torch engine at once).
        meta: its checkpoint metadata (input bands, tasks).
        device, precision: where and how it runs.
        compile: ``torch.compile`` the torch engine's model.
        threads: CPU threads and streams of the OpenVINO engine.
        weights_key: the checkpoint's fingerprint (keys the OpenVINO cache without hashing the weights again).
    """
    tasks = tuple(meta.model.tasks)
    if engine == "openvino":
        return OpenVINOEngine(model, meta.model.in_channels, tasks, precision, threads=threads,
                              weights_key=weights_key)
    prepared = inference_model(resolve_model(model), device)
    return TorchEngine(compile_model(prepared) if compile else prepared, prepared, device, precision, tasks)


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


def model_outputs(model: nn.Module | CheckpointModel, tasks: Sequence[str]) -> tuple[str, ...]:
    """The keys of ``model``'s output dict in order: its ``outputs`` (a D3-Net: the tasks, plus
    ``height_scale`` for an aleatoric head), else ``tasks``.
    """
    return tuple(getattr(model, "outputs", None) or tasks)


def _graph_output(task: str, t: torch.Tensor) -> torch.Tensor:
    """Output ``task`` of a traced graph (forward or decoder): ``(1, C, h, w)`` → ``(1, h, w, C)`` for
    :data:`FORWARD_CHANNELS_LAST`.
    """
    return t.permute(0, 2, 3, 1) if task in FORWARD_CHANNELS_LAST else t


def _as_planes(task: str, t: torch.Tensor) -> torch.Tensor:
    """A graph's output ``task`` in the models' ``(B, C, h, w)`` order: a view of a channels-last ``(B, h, w, C)``
    array for :data:`FORWARD_CHANNELS_LAST` (no copy: the softmax and the MC class kernel read it channels last).
    """
    return t.permute(0, 3, 1, 2) if task in FORWARD_CHANNELS_LAST else t


class _Forward(nn.Module):
    def __init__(self, model: nn.Module, tasks: Sequence[str]) -> None:
        super().__init__()
        self.model, self.tasks = model, model_outputs(model, tasks)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(x)
        return tuple(_graph_output(t, out[t]) for t in self.tasks)


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
        return tuple(_graph_output(t, out[t]) for t in self.tasks)


# ---- engines ----------------------------------------------------------------------------------------
class OpenVINOEngine:
    """The model compiled by OpenVINO for the CPU (see the module docstring).

    Args:
        model: the D3-Net as loaded, or a :class:`~aerialmtl.inference.model_record.CheckpointModel` (then the
            weights are loaded only when a cache entry is missing and the model must be converted).
        in_channels: its input bands.
        tasks: its tasks, in output order.
        precision: ``"bf16"`` or ``"fp32"``.
        cache_dir: where the IR and compiled models go (default :func:`cache_root`/fingerprint; nothing is
            cached with ``cache=False``; :class:`~aerialmtl.inference.engine_cache.EngineCache`).
        cache: keep converted and compiled models on disk.
    """

    name = "openvino"

    def __init__(self, model: nn.Module | CheckpointModel, in_channels: int, tasks: Sequence[str], precision: str,
                 cache_dir: str | Path | None = None, cache: bool = True, threads: CpuThreads | None = None,
                 weights_key: str | None = None) -> None:
        ov = runtime.import_openvino()
        self.ov = ov
        self.raw_model = model
        self._model: nn.Module | None = None
        self.in_channels = in_channels
        self.tasks = model_outputs(model, tasks)  # output order of the converted graphs
        self.precision = precision
        #: Threads and streams the model is compiled for (:func:`aerialmtl.runtime.resolve_threads`).
        self.threads = threads if threads is not None else resolve_threads()
        self._sites: list[DropoutSite] | None = None
        self.core = ov.Core()
        self.cache_dir: Path | None = None
        if cache:
            cfg = getattr(model, "cfg", "")
            extra = f"{__version__}|{ov.__version__}|{in_channels}|{self.tasks}|{cfg}|{CONVERT_SIZE}|{GRAPH_OUTPUTS}"
            if cache_dir is not None:
                self.cache_dir = Path(cache_dir)
            elif weights_key is not None:  # the checkpoint's hash, computed once by the caller
                key = hashlib.blake2b(f"{weights_key}|folded|{extra}".encode(), digest_size=12).hexdigest()
                self.cache_dir = cache_root() / key
            else:
                self.cache_dir = cache_root() / fingerprint(resolve_model(model), extra)
        self.cache = EngineCache(self.cache_dir)
        self._models: dict[str, openvino.Model] = {}
        self._compiled: dict[tuple[str, int, int], _Requests] = {}
        self._lock = threading.Lock()
        self._buffers: list[list[np.ndarray]] = []
        self._buffers_key: tuple[Any, ...] | None = None
        self._pool = _BufferPool(limit=self.threads.streams + 2)

    @property
    def model(self) -> nn.Module:
        """The model prepared for conversion (BatchNorm folded; made on first use: a warm cache never
        needs it).
        """
        if self._model is None:
            self._model = inference_model(resolve_model(self.raw_model), torch.device("cpu"))
        return self._model

    @property
    def sites(self) -> list[DropoutSite]:
        """The decoder's dropout layers (found on first use: only MC dropout needs them; folding does not
        move them, so the model as loaded is probed).
        """
        if self._sites is None:
            if isinstance(self.raw_model, CheckpointModel):  # recorded when the checkpoint was first loaded
                self._sites = list(self.raw_model.record.sites)
            else:
                self._sites = dropout_sites(self.raw_model, self.in_channels)
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

    def _requests(self, part: str, h: int, w: int) -> _Requests:
        """The infer requests of ``part`` compiled for ``h × w`` windows (compiled on first use).

        A compiled model in the cache is imported without reading the converted model (IR) at all; only a
        missing one is compiled from the IR (which, missing too, is converted from the torch model).
        """
        key = (part, h, w)
        with self._lock:
            if key not in self._compiled:
                config = self.compile_config()
                hint, n = config["INFERENCE_PRECISION_HINT"], self.threads
                name = f"{part}.{h}x{w}.{hint}.t{n.threads}s{n.streams}.blob"
                compiled, blob = self._import(name, config)
                if compiled is None:
                    compiled = self._compile(self._shaped(part, h, w), name, config)
                self._compiled[key] = _Requests(compiled, self.threads.streams, keep=blob)
            return self._compiled[key]

    def _shaped(self, part: str, h: int, w: int) -> openvino.Model:
        """The converted ``part`` reshaped for ``h × w`` windows (a copy)."""
        model = self._ov_model(part).clone()
        shapes: dict[int, list[int]] = {0: [1, self.in_channels, h, w]}
        if part == "decode":
            feats = self._feature_shapes(h, w)
            shapes = {k: list(s) for k, s in enumerate(feats)}
            shapes.update({len(feats) + k: [1, *site.shape(h, w)] for k, site in enumerate(self.sites)})
        model.reshape(shapes)
        return model

    def compile_config(self) -> dict[str, Any]:
        """OpenVINO's CPU settings: precision, threads and streams (:attr:`threads`), no pinning of threads to
        cores (a core another process holds would stall the stream pinned to it).
        """
        hint = "bf16" if self.precision == "bf16" else "f32"
        return {"INFERENCE_PRECISION_HINT": hint, "INFERENCE_NUM_THREADS": self.threads.threads,
                "NUM_STREAMS": self.threads.streams, "ENABLE_CPU_PINNING": False}

    def _serialize(self, model: openvino.Model) -> list[bytes]:
        """An IR's XML and weights as bytes (through a private temporary folder: OpenVINO writes files)."""
        import tempfile

        with tempfile.TemporaryDirectory(prefix="aerialmtl-ov-") as tmp:
            xml = Path(tmp) / "model.xml"
            self.ov.save_model(model, str(xml), compress_to_fp16=False)
            return [xml.read_bytes(), xml.with_suffix(".bin").read_bytes()]

    def _import(self, name: str, config: dict[str, Any]) -> tuple[Any | None, np.ndarray | None]:
        """The compiled model of cache entry ``name`` and the bytes it was imported from, or ``(None, None)``
        when it is missing, corrupt (removed, with a warning) or refused by this OpenVINO (a warning).

        The model is imported from a Tensor over the bytes as read (no copy into a stream first). OpenVINO
        keeps using that memory after the import (its weights, measured: freed bytes gave other maps), so the
        bytes must live as long as the compiled model: the caller keeps them with its requests.
        """
        cached = self.cache.read_one(name)
        if cached is not None:
            try:
                return self.core.import_model(self.ov.Tensor(cached, shared_memory=True), "CPU", config), cached
            except RuntimeError as exc:  # a whole entry OpenVINO still refuses (e.g. written by another build)
                warnings.warn(f"cached OpenVINO model '{self.cache.folder}/{name}' could not be loaded "
                              f"({' '.join(str(exc).split())[:120]}); rebuilding it", UserWarning, stacklevel=3)
        return None, None

    def _compile(self, model: openvino.Model, name: str, config: dict[str, Any]) -> Any:
        """``model`` compiled for the CPU, stored as cache entry ``name``."""
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
    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, C, h, w) normalised → ``{task: (B, C_t, h, w)}`` (float32; the windows run in parallel streams)."""
        h, w = x.shape[-2:]
        reqs = self._requests("forward", h, w)
        jobs = [reqs.start({0: x[n:n + 1].contiguous().numpy()}) for n in range(x.shape[0])]
        outs = [job.outputs() for job in jobs]
        return {task: _as_planes(task, torch.cat([torch.from_numpy(o[k]) for o in outs]))
                for k, task in enumerate(self.tasks)}

    def encode(self, x: torch.Tensor) -> list[np.ndarray]:
        """(1, C, h, w) normalised → the encoder features (numpy, for :meth:`decode`)."""
        return self._requests("encode", *x.shape[-2:]).start({0: x.contiguous().numpy()}).outputs()

    def decode(self, feats: list[np.ndarray], masks: list[torch.Tensor], h: int, w: int) -> list[torch.Tensor]:
        """One image's features and one sample's masks → its outputs, in task order (``(1, C_t, h, w)``)."""
        outs = self._start_decode(feats, masks, h, w).outputs()
        return [_as_planes(task, torch.from_numpy(o)) for task, o in zip(self.tasks, outs)]

    def _start_decode(self, feats: list[np.ndarray], masks: list[torch.Tensor], h: int, w: int,
                      dest: list[np.ndarray] | None = None) -> _Job:
        inputs: dict[int, np.ndarray] = dict(enumerate(feats))
        inputs.update({len(feats) + k: m.numpy() for k, m in enumerate(masks)})
        return self._requests("decode", h, w).start(inputs, dest)

    def submit(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
               sample_batch: int) -> Pending:
        """Start the statistics of a normalised (B, C, h, w) batch; ``.result()`` waits for them.

        T = 1: each window's forward pass starts at once on a free stream (waiting for the oldest running
        one when all are busy), so the caller stitches one batch while the next runs. T > 1: the work runs in
        ``result()``, the samples of a window spread over the streams (:meth:`statistics`).
        """
        x = x.float()
        if samples > 1:
            return _Deferred(lambda: self.statistics(x, keys, samples, seed, sample_batch))
        h, w = x.shape[-2:]
        reqs = self._requests("forward", h, w)
        jobs = [reqs.start({0: x[n:n + 1].contiguous().numpy()}, self._pool.take(reqs.shapes))
                for n in range(x.shape[0])]
        return _Forward1(self.tasks, jobs, self._pool)

    def statistics(self, x: torch.Tensor, keys: Sequence[int], samples: int, seed: int,
                   sample_batch: int) -> McStatistics:
        """Normalised (B, C, h, w) batch → statistics of each window (as the torch path).

        T > 1: the encoder once per window, then the T decoder samples of the batch in chunks of
        ``sample_batch`` samples, started in order on the streams ahead of the accumulation (up to one
        sample per stream of the next chunk runs while the host accumulates the current one). Each sample's
        outputs are copied straight into one of two chunk buffers reused from window to window (fresh
        buffers per sample cost more in page faults than the copies themselves; bench/RESULTS.md).
        """
        x = x.float()
        if samples == 1:
            return self.submit(x, keys, samples, seed, sample_batch).result()
        b, _, h, w = x.shape
        chunk = max(1, min(int(sample_batch), samples))
        feats = [self.encode(x[n:n + 1]) for n in range(b)]
        reqs = self._requests("decode", h, w)
        buffers = self._chunk_buffers(reqs.shapes, chunk * b)
        order = [(t, n) for t in range(samples) for n in range(b)]  # sample-major, as accumulate_samples wants
        jobs: list[_Job] = []

        def start_until(count: int) -> None:
            while len(jobs) < min(count, len(order)):
                i = len(jobs)
                t, n = order[i]
                row = i - (t // chunk) * chunk * b
                dest = [buf[row:row + 1] for buf in buffers[(t // chunk) % 2]]
                jobs.append(self._start_decode(feats[n], dropout_masks(self.sites, h, w, seed, keys[n], t), h, w,
                                               dest))

        def decode_chunk(done: int, s: int) -> dict[str, torch.Tensor]:
            first, last = done * b, (done + s) * b
            start_until(last)
            for i in range(first, last):
                jobs[i].collect()
                jobs[i] = _DONE
            start_until(last + min(chunk * b, self.threads.streams))  # the engine runs on while the host accumulates
            out = buffers[(done // chunk) % 2]
            return {task: _as_planes(task, torch.from_numpy(out[k][:s * b])) for k, task in enumerate(self.tasks)}

        return accumulate_samples(decode_chunk, samples, chunk, b)

    def _chunk_buffers(self, shapes: Sequence[tuple[int, ...]], rows: int) -> list[list[np.ndarray]]:
        """Two sets of float32 buffers, ``rows × shape[1:]`` per output (kept for the next window of the same
        shape; one shape at a time).
        """
        key = (rows, *[tuple(s) for s in shapes])
        if self._buffers_key != key:
            self._buffers = [[np.empty((rows, *s[1:]), np.float32) for s in shapes] for _ in range(2)]
            self._buffers_key = key
        return self._buffers


# ---- requests in flight -------------------------------------------------------------------------------
class _Job:
    """One inference started on a request of :class:`_Requests`; :meth:`outputs` waits for it (once).

    With ``direct``, the request writes its outputs straight into ``dest`` (set as its output tensors): nothing
    is copied when it is collected.
    """

    def __init__(self, owner: _Requests | None = None, slot: int = 0, dest: list[np.ndarray] | None = None,
                 direct: bool = False) -> None:
        self.owner, self.slot, self.dest, self.direct = owner, slot, dest, direct
        self._outputs: list[np.ndarray] | None = None

    def collect(self) -> None:
        """Wait for the request and copy its outputs out (into ``dest`` when given, unless the request wrote
        there itself), freeing the request.
        """
        if self._outputs is not None or self.owner is None:
            return
        req = self.owner.requests[self.slot]
        req.wait()
        if self.direct:
            assert self.dest is not None
            self._outputs = self.dest
        else:
            tensors = [req.get_output_tensor(k).data for k in range(len(req.model_outputs))]
            if self.dest is not None:
                for d, t in zip(self.dest, tensors):
                    np.copyto(d, t)
                self._outputs = self.dest
            else:
                self._outputs = [np.array(t, copy=True) for t in tensors]
        self.owner.running[self.slot] = None

    def outputs(self) -> list[np.ndarray]:
        """The model's outputs, in order (float32 numpy)."""
        self.collect()
        assert self._outputs is not None
        return self._outputs


_DONE = _Job()


class _Requests:
    """The infer requests of one compiled model, one per stream, used in turn: a new job takes the next
    request, first collecting the job still on it (the oldest, as jobs take similar times).
    """

    def __init__(self, compiled: Any, n: int, keep: np.ndarray | None = None) -> None:
        ov = runtime.import_openvino()
        #: The bytes ``compiled`` was imported from: OpenVINO reads them while it runs (:meth:`OpenVINOEngine._import`).
        self.keep = keep
        self._tensor = ov.Tensor
        self.requests = [compiled.create_infer_request() for _ in range(max(1, n))]
        #: The outputs' shapes (one image).
        self.shapes = [tuple(o.get_shape()) for o in compiled.outputs]
        self.running: list[_Job | None] = [None] * len(self.requests)
        # each request's own output tensors, put back when a job without ``dest`` follows one that wrote into
        # the caller's arrays (which the caller may be reading by then)
        self._own = [[req.get_output_tensor(k) for k in range(len(self.shapes))] for req in self.requests]
        self._lent = [False] * len(self.requests)
        self._next = 0

    def start(self, inputs: dict[int, np.ndarray], dest: list[np.ndarray] | None = None) -> _Job:
        """Start one inference on ``inputs`` (copied into the request) and return its job. With ``dest`` (one
        float32 array per output, of its shape), the outputs end up there: written by the request itself when
        the arrays are C-contiguous (no copy), else copied when the job is collected.
        """
        slot = self._next
        self._next = (slot + 1) % len(self.requests)
        busy = self.running[slot]
        if busy is not None:
            busy.collect()
        req = self.requests[slot]
        direct = dest is not None and all(
            d.dtype == np.float32 and d.flags.c_contiguous and d.flags.writeable and tuple(d.shape) == s
            for d, s in zip(dest, self.shapes))
        if direct:
            assert dest is not None
            for k, d in enumerate(dest):
                req.set_output_tensor(k, self._tensor(d, shared_memory=True))
            self._lent[slot] = True
        elif self._lent[slot]:
            for k, t in enumerate(self._own[slot]):
                req.set_output_tensor(k, t)
            self._lent[slot] = False
        job = _Job(self, slot, dest, direct)
        self.running[slot] = job
        req.start_async(inputs)
        return job


class Pending(Protocol):
    """Statistics of a batch being computed; :meth:`result` waits for them."""

    def result(self) -> McStatistics:
        """The statistics, once computed (waits for them)."""
        ...


class Done:
    """Statistics already computed (the torch engine's, which runs synchronously)."""

    def __init__(self, stats: McStatistics) -> None:
        self.stats = stats

    def result(self) -> McStatistics:
        """The statistics."""
        return self.stats


class _Deferred:
    """Statistics computed when asked for."""

    def __init__(self, compute: Callable[[], McStatistics]) -> None:
        self.compute = compute

    def result(self) -> McStatistics:
        return self.compute()


class _Forward1:
    """The T = 1 statistics of a batch whose forward passes are running (one job per window); the output
    buffers go back to ``pool`` once the statistics are made from them.
    """

    def __init__(self, tasks: tuple[str, ...], jobs: list[_Job], pool: _BufferPool) -> None:
        self.tasks, self.jobs, self.pool = tasks, jobs, pool

    def result(self) -> McStatistics:
        outs = [job.outputs() for job in self.jobs]
        raw = {task: _as_planes(task, torch.cat([torch.from_numpy(o[k]) for o in outs]) if len(outs) > 1
                                else torch.from_numpy(outs[0][k])) for k, task in enumerate(self.tasks)}
        stats = single_pass_statistics(raw)
        if stats.height_mean is not None:  # a view of the buffer, which goes back to the pool
            stats.height_mean = stats.height_mean.clone()
        for o in outs:
            self.pool.give(o)
        return stats


class _BufferPool:
    """Output buffers of T = 1 windows, reused: a fresh 80 MiB array per window (1024², 20 classes) costs
    its page faults every time. Holds at most ``limit`` sets, of any shapes.
    """

    def __init__(self, limit: int = 4) -> None:
        self.limit = limit
        self.free: list[list[np.ndarray]] = []

    def take(self, shapes: Sequence[tuple[int, ...]]) -> list[np.ndarray]:
        """A set of float32 arrays of ``shapes`` (reused when one is free)."""
        want = [tuple(s) for s in shapes]
        for k, bufs in enumerate(self.free):
            if [b.shape for b in bufs] == want:
                return self.free.pop(k)
        return [np.empty(s, np.float32) for s in want]

    def give(self, bufs: list[np.ndarray]) -> None:
        """Return a set once nothing reads it any more (the oldest free set is dropped beyond ``limit``)."""
        self.free.append(bufs)
        if len(self.free) > self.limit:
            self.free.pop(0)


__all__ = ["CONVERT_SIZE", "ENGINES", "Done", "Engine", "EngineName", "OPENVINO_INSTALL", "OpenVINOEngine", "Pending",
           "TorchEngine", "build_engine", "cache_root", "compile_model", "fingerprint", "openvino_available",
           "resolve_engine"]
