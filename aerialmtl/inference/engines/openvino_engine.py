"""The ``openvino`` engine: the (loaded, BatchNorm-folded) model converted with ``openvino.convert_model`` and
compiled for the CPU, once per window shape (:mod:`aerialmtl.inference.engines`, the package's docstring).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import threading
import warnings
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl._version import __version__
from aerialmtl.errors import InputError
from aerialmtl.inference.engine_cache import EngineCache
from aerialmtl.inference.engines.base import Deferred, EngineSetup, EngineSpec, Pending
from aerialmtl.inference.engines.openvino_graphs import (
    CONVERT_SIZE,
    GRAPH_OUTPUTS,
    _as_planes,
    _Decoder,
    _Encoder,
    _Forward,
    cache_root,
    fingerprint,
    model_outputs,
)
from aerialmtl.inference.engines.openvino_requests import _DONE, _BufferPool, _Forward1, _Job, _Requests
from aerialmtl.inference.model_record import RECORDS, CheckpointModel, resolve_model
from aerialmtl.models.d3net import D3Net, encode_features, inference_model
from aerialmtl.models.familiarity import FeatureDensity
from aerialmtl.models.mc_dropout import DropoutSite, McStatistics, accumulate_samples, dropout_masks, dropout_sites
from aerialmtl.quiet import ignoring_warnings
from aerialmtl.runtime import CpuThreads, resolve_threads
from aerialmtl.stores import warn_once

if TYPE_CHECKING:
    import openvino

#: The command that installs the OpenVINO engine (named in the error when it is missing).
OPENVINO_INSTALL = "pip install openvino"


def openvino_available() -> bool:
    """Whether OpenVINO is installed, without importing it (~0.5 s and its threads, which a run that ``auto``
    gives to torch does not need): its import is :func:`aerialmtl.runtime.import_openvino`, when the engine is
    built. A broken install fails there, and ``auto`` falls back to torch.
    """
    if "openvino" in sys.modules:  # imported already (None: an import that failed, or was blocked)
        return sys.modules["openvino"] is not None
    try:
        return importlib.util.find_spec("openvino") is not None
    except (ImportError, ValueError):
        return False


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
        density: the checkpoint's feature density: each window's ``unfamiliarity`` from the encoder graph's
            outputs (at T = 1 the encoder graph runs once more per window for it).
    """

    name = "openvino"

    def __init__(self, model: nn.Module | CheckpointModel, in_channels: int, tasks: Sequence[str], precision: str,
                 cache_dir: str | Path | None = None, cache: bool = True, threads: CpuThreads | None = None,
                 weights_key: str | None = None, density: FeatureDensity | None = None) -> None:
        ov = runtime.import_openvino()
        self.density = density
        self.ov = ov
        self.raw_model = model
        self._model: nn.Module | None = None
        self.in_channels = in_channels
        self.tasks = model_outputs(model, tasks)  # output order of the converted graphs
        self.precision = precision
        self._tag: str | None = None
        #: Threads and streams the model is compiled for (:func:`aerialmtl.runtime.resolve_threads`).
        self.threads = threads if threads is not None else resolve_threads()
        self._sites: list[DropoutSite] | None = None
        self.core = runtime.openvino_core()  # one per process (see there: a Core per engine corrupted memory)
        self.cache_dir: Path | None = None
        if cache:
            cfg = getattr(model, "cfg", "")
            extra = f"{__version__}|{ov.__version__}|{in_channels}|{self.tasks}|{cfg}|{CONVERT_SIZE}|{GRAPH_OUTPUTS}"
            if cache_dir is not None:
                self.cache_dir = Path(cache_dir)
            elif weights_key is not None:  # the checkpoint's hash, computed once by the caller
                key = hashlib.blake2b(f"{weights_key}|folded|{extra}".encode(), digest_size=12).hexdigest()
                root = cache_root()
                self.cache_dir = None if root is None else root / key
            elif (root := cache_root()) is not None:
                self.cache_dir = root / fingerprint(resolve_model(model), extra)
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
    def net(self) -> nn.Module:
        """The model as given (loaded from its checkpoint when it was not yet; nothing measures it on a CPU)."""
        return resolve_model(self.raw_model)

    def ahead(self, samples: int) -> int:
        """One batch per stream at T = 1 (:meth:`submit` starts the windows and returns); none for MC dropout."""
        return self.threads.streams if samples == 1 else 0

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
            feats = encode_features(self.model, x)
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
            # shape checks traced as constants
            with torch.enable_grad(), ignoring_warnings(torch.jit.TracerWarning):  # type: ignore[attr-defined]
                traced = torch.jit.trace(module.eval(), example, check_trace=False, strict=False)
            model = self.ov.convert_model(traced)
            if self.cache.enabled:
                ir = self.cache.serialise(lambda xml: self.ov.save_model(model, str(xml), compress_to_fp16=False))
                if ir is not None:
                    self.cache.write(f"{part}.ir", ir)
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
                name = self._entry_name(part, h, w)
                compiled, blob = self._import(name, config)
                if compiled is None:
                    compiled = self._compile(self._shaped(part, h, w), name, config)
                self._compiled[key] = _Requests(compiled, self.threads.streams, keep=blob)
            return self._compiled[key]

    def _entry_name(self, part: str, h: int, w: int) -> str:
        """The cache entry of ``part`` compiled for ``h × w`` windows at this precision, threads, streams and CPU."""
        hint, n = self.compile_config()["INFERENCE_PRECISION_HINT"], self.threads
        return f"{part}.{h}x{w}.{hint}.t{n.threads}s{n.streams}.{self._cpu_tag()}.blob"

    def cached(self, h: int, w: int, samples: int) -> bool:
        """Whether every graph that ``h × w`` windows at ``samples`` MC samples run is compiled in the cache (a
        run without them converts and compiles first: :func:`~aerialmtl.inference.engine_choice.auto_engine`).
        """
        parts = {"forward"} if samples == 1 else {"encode", "decode"}
        if self.density is not None:
            parts.add("encode")
        return self.cache.enabled and all(self.cache.path(self._entry_name(p, h, w)).is_file() for p in parts)

    def _cpu_tag(self) -> str:
        """A short tag of the kind of CPU a compiled model is for.

        The machine, its native bf16 units and the oneDNN ISA cap (:func:`aerialmtl.runtime.cpu_bf16_flags`).
        Compiled models are CPU-specific: a cache folder shared by machines of several kinds (a home folder on a
        cluster's network drive, or a run under ``.ci/as-cpu``) keeps one entry per kind instead of rebuilding,
        with a warning, at every switch.
        """
        if self._tag is None:
            cap = os.environ.get("ONEDNN_MAX_CPU_ISA", "").strip().upper()
            key = f"{os.uname().machine}|{','.join(runtime.cpu_bf16_flags())}|{cap}"
            self._tag = hashlib.sha256(key.encode()).hexdigest()[:8]
        return self._tag

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
        hint = "bf16" if self.precision == "bf16" and runtime.cpu_bf16_flags() else "f32"
        if self.precision == "bf16" and hint == "f32":  # as OpenVINO does on such a CPU, but said
            warn_once("--precision bf16: this CPU has no bf16 units (no AVX-512-BF16 or AMX), so OpenVINO computes "
                      "in fp32 (use --precision auto or fp32 to say so)")
        return {"INFERENCE_PRECISION_HINT": hint, "INFERENCE_NUM_THREADS": self.threads.threads,
                "NUM_STREAMS": self.threads.streams, "ENABLE_CPU_PINNING": False}

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
            return Deferred(lambda: self.statistics(x, keys, samples, seed, sample_batch))
        h, w = x.shape[-2:]
        unfamiliarity = self._unfamiliarity(x) if self.density is not None else None
        reqs = self._requests("forward", h, w)
        jobs = [reqs.start({0: x[n:n + 1].contiguous().numpy()}, self._pool.take(reqs.shapes))
                for n in range(x.shape[0])]
        return _Forward1(self.tasks, jobs, self._pool, unfamiliarity)

    def _unfamiliarity(self, x: torch.Tensor, feats: Sequence[list[np.ndarray]] | None = None) -> torch.Tensor:
        """(B, h, w) unfamiliarity of a normalised batch from each window's encoder outputs (``feats``, else the
        encoder graph run here).
        """
        assert self.density is not None
        size = (x.shape[-2], x.shape[-1])
        if feats is None:
            feats = [self.encode(x[n:n + 1]) for n in range(x.shape[0])]
        return torch.cat([self.density.unfamiliarity(f, size) for f in feats])

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

        stats = accumulate_samples(decode_chunk, samples, chunk, b)
        if self.density is not None:
            stats.unfamiliarity = self._unfamiliarity(x, feats)
        return stats

    def _chunk_buffers(self, shapes: Sequence[tuple[int, ...]], rows: int) -> list[list[np.ndarray]]:
        """Two sets of float32 buffers, ``rows × shape[1:]`` per output (kept for the next window of the same
        shape; one shape at a time).
        """
        key = (rows, *[tuple(s) for s in shapes])
        if self._buffers_key != key:
            self._buffers = [[np.empty((rows, *s[1:]), np.float32) for s in shapes] for _ in range(2)]
            self._buffers_key = key
        return self._buffers


def _convertible(model: nn.Module | CheckpointModel) -> bool:
    return isinstance(model, (D3Net, CheckpointModel))  # a checkpoint's model is a D3-Net


def openvino_unusable(device: torch.device, model: nn.Module | CheckpointModel) -> InputError | None:
    """Why the OpenVINO engine cannot run ``model`` on ``device`` (on CUDA, another model than a D3-Net, not
    installed: one line naming :data:`OPENVINO_INSTALL`), or ``None``.
    """
    if device.type != "cpu":
        return InputError(f"‹engine=openvino› runs on the CPU, not on {device}; pass ‹device=cpu› or ‹engine=torch›",
                          param="engine")
    if not _convertible(model):
        return InputError(f"‹engine=openvino› converts D3-Net models only, not {type(model).__name__}; "
                          "pass ‹engine=torch›", param="engine")
    if not openvino_available():
        return InputError(f"‹engine=openvino› needs OpenVINO, which is not installed; install it with "
                          f"`{OPENVINO_INSTALL}` or pass ‹engine=torch›")
    return None


def build_openvino(setup: EngineSetup) -> OpenVINOEngine:
    """The OpenVINO engine of ``setup`` (its cache keyed by ``setup.weights_key`` when given)."""
    return OpenVINOEngine(setup.model, setup.meta.model.in_channels, setup.tasks, setup.resolved.precision,
                          threads=setup.resolved.threads, weights_key=setup.weights_key,
                          density=setup.meta.familiarity)


def openvino_cached(setup: EngineSetup, shapes: Collection[tuple[int, int]], samples: int) -> bool:
    """Whether the cache of ``setup``'s engine holds every graph that windows of ``shapes`` run at ``samples`` MC
    samples (:meth:`OpenVINOEngine.cached`; building the engine compiles nothing).
    """
    root = cache_root()
    if root is None or not root.is_dir() or not any(p.is_dir() and p.name != RECORDS for p in root.iterdir()):
        # nothing compiled here yet: cold, told without importing OpenVINO and making its Core (a second of a run
        # that auto then gives to torch)
        return False
    engine = build_openvino(setup)
    return all(engine.cached(h, w, samples) for h, w in shapes)


def openvino_records() -> Path | None:
    """The folder of the checkpoint records beside the engine cache (:func:`cache_root`), where OpenVINO is
    installed.
    """
    return cache_root() if openvino_available() else None


#: What converting and compiling the full D3-Net for one window shape costs, in window megapixels of the torch
#: engine (fp32) on the same CPU. Measured on an AVX2 AMD Zen 3 (issue 46): a first 2048² T = 1 predict (4.9 window
#: megapixels) ran 0.55× the torch engine, the second 1.69×, so the compilation took (1/0.55 − 1/1.69) ≈ 1.23
#: torch runs of that job ≈ 6 megapixels. Compilation and the torch engine both slow down with the CPU, so the
#: cost is kept in the torch engine's work rather than in seconds.
COMPILE_TORCH_MPX = 6.0
#: The speed over the torch engine (fp32) expected on a CPU kind the table has not measured: the smallest end-to-end
#: speed-up measured on any kind (1.14× on AVX-512-BF16, aerialmtl/resources/engine_choice.yaml). It is what
#: weighs the compilation there: on an Intel Ice Lake (AVX-512 without BF16, not in the table) a first 2048² T = 1
#: predict took 1.13× the torch engine's time at load 2, the cold compilation paid for a job too small to earn it.
EXPECTED_SPEEDUP = 1.14

#: The OpenVINO engine's entry of the registry (:mod:`aerialmtl.inference.engines.names`).
SPEC = EngineSpec("openvino", "OpenVINO", build_openvino, openvino_unusable, speedup=EXPECTED_SPEEDUP,
                  compile_mpx=COMPILE_TORCH_MPX, cached=openvino_cached, record_root=openvino_records,
                  precisions=("fp32", "bf16", "int8"))

__all__ = ["COMPILE_TORCH_MPX", "EXPECTED_SPEEDUP", "OPENVINO_INSTALL", "SPEC", "OpenVINOEngine", "build_openvino",
           "openvino_available", "openvino_cached", "openvino_records", "openvino_unusable"]
