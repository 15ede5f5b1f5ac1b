"""Where and how the model runs, for training and prediction alike: one place for each choice.

* **device** — :func:`resolve_device`: ``auto`` → CUDA when available, else the CPU; under ``torchrun``
  each process on CUDA takes ``cuda:LOCAL_RANK``.
* **precision** — :func:`native_bf16` is the one check whether a device computes bf16 natively (a CUDA
  GPU with bf16; a CPU with AMX-BF16 or AVX-512-BF16 — Intel Sapphire Rapids and later, AMD Zen 4 and
  later). CPUs without them emulate bf16 convolutions 10–100× slower than fp32. :func:`resolve_precision`
  turns ``auto`` into a precision from it (the callers say which device types may use bf16 under
  ``auto``: what was measured faster there, bench/RESULTS.md); :func:`autocast` applies it to torch code.
* **compile** — :class:`CompileFallback`: ``torch.compile`` of chosen methods of a module, falling back to
  the eager method (one warning) where compilation fails.
* **torchrun** — :class:`Torchrun`: ``RANK``/``WORLD_SIZE``/``LOCAL_RANK`` read once, the device of the
  process, joining the process group (gloo on CPUs, NCCL on GPUs) with a stated timeout
  (:data:`COLLECTIVE_TIMEOUT` for training, whose collectives are in step; :data:`SHARE_TIMEOUT` for
  prediction, whose ranks wait for each other's whole share of the work at the end).
* **GDAL** — :func:`gdal_env`: a bounded block cache while rasters are streamed (tile, predict, buildings).
* **OpenVINO** — :func:`import_openvino`: the one ``import openvino`` of the package, without OpenVINO's usage
  telemetry (aerialmtl makes no network call, and writes in the user's home only its caches).
* **CPU threads** — :func:`resolve_threads`: the inference threads of a process (an option, else
  :data:`THREADS_ENV`, else torch's own count) and how they are split into engine streams
  (:class:`CpuThreads`).

The trainer (:mod:`aerialmtl.training.trainer`, :mod:`aerialmtl.training.distributed`) and the predictor
(:mod:`aerialmtl.inference.predict`, :mod:`aerialmtl.inference.jobs`) both use this module.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import functools
import os
import sys
import threading
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Literal, TypeVar

import rasterio
import torch
import torch.distributed as dist
from torch import nn

from aerialmtl.cpuinfo import cpu_fields, cpu_flags, usable_cpus
from aerialmtl.errors import AerialMTLError, InputError, PeerFailure, cause
from aerialmtl.stores import warn_once

Precision = Literal["auto", "bf16", "fp32"]
Resolved = Literal["bf16", "fp32"]

#: How long a training collective may wait for a peer before the run is declared hung (the ranks run
#: in step; cache builds are locked per file, not by collectives, so this only bounds a real hang).
COLLECTIVE_TIMEOUT = _dt.timedelta(minutes=30)
#: How long a prediction rank waits for the others at the end of its share (they may have hours of
#: work left: the shares are equal in pixels, not in time).
SHARE_TIMEOUT = _dt.timedelta(days=7)
#: GDAL's block cache (``GDAL_CACHEMAX``) while a command streams rasters, **in bytes**, per command: the one
#: place these sizes are set (:func:`gdal_env`); a ``GDAL_CACHEMAX`` environment variable wins.
#:
#: * ``tile``: 128 MiB, keeps memory flat on huge rasters;
#: * ``buildings``: 64 MiB, every block is read once, so a cache larger than one block row of tiles only
#:   grows with the raster (GDAL's default is 5 % of the RAM);
#: * ``predict``: 32 **bytes**, i.e. practically no block cache. Earlier versions meant 32 MB (GDAL reads a
#:   ``GDAL_CACHEMAX`` *configuration option* below 100000 as megabytes), but ``rasterio.Env`` hands the
#:   number to ``GDALSetCacheMax64``, which takes bytes: predict has always run this way (its reader threads
#:   read whole windows, and the writer's staging files are uncompressed, written block by block). Kept: an
#:   earlier attempt at 32 MiB changed where a full disk surfaces during the staging writes (the one-line
#:   message test failed) and it was never benchmarked; changing it is a change of behaviour, not a unit fix.
GDAL_CACHE_BYTES: dict[str, int] = {"tile": 128 * 2**20, "buildings": 64 * 2**20, "predict": 32}
#: CPU flags (``/proc/cpuinfo``) of native bf16 matrix arithmetic.
BF16_CPU_FLAGS = ("amx_bf16", "avx512_bf16")
#: Environment variable that replaces the CPU probe of :func:`cpu_bf16_flags` (read on first use).
CPU_FLAGS_ENV = "AERIALMTL_CPU_BF16_FLAGS"
#: Environment variable with the inference threads of ``predict`` (a number, or ``auto``); ``--threads`` wins.
THREADS_ENV = "AERIALMTL_THREADS"
#: Most inference streams of one process under ``auto``: each stream holds its own window's activations
#: (~0.3-1 GiB for a 1024² window of the full D3-Net), so many-core CPUs get wider streams, not more.
MAX_STREAMS = 4


# ---- device -------------------------------------------------------------------------------------
def resolve_device(device: str, local_rank: int = 0, error: type[AerialMTLError] = InputError) -> torch.device:
    """``auto`` → ``cuda`` when available, else ``cpu``; ``cuda`` under torchrun → ``cuda:local_rank``.

    Raises:
        ``error`` (InputError by default; the trainer passes ConfigError): CUDA asked for but absent, or
        an unknown device.
    """
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise error(f"‹device={device}› but no CUDA GPU is available; pass ‹device=cpu› or ‹device=auto›",
                    param="device")
    if device != "cpu" and not device.startswith("cuda"):
        raise error(f"‹device={device}› is not supported; use auto, cpu or cuda", param="device")
    if device == "cuda":
        return torch.device("cuda", local_rank)
    return torch.device(device)


# ---- precision ----------------------------------------------------------------------------------
#: ``ONEDNN_MAX_CPU_ISA`` values (upper case) that leave oneDNN (in torch and OpenVINO) without bf16 kernels, or
#: without AMX: a CPU capped so computes as one without those units, whatever its flags say.
_NO_BF16_ISAS = ("SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2", "AVX512_CORE", "AVX512_CORE_VNNI")
_NO_AMX_ISAS = ("AVX512_CORE_BF16", "AVX10_1_512", "AVX512_CORE_FP16")


def _capped_away() -> set[str]:
    """The bf16 flags that ``ONEDNN_MAX_CPU_ISA`` (an emulated smaller CPU) takes away."""
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA", "").strip().upper()
    if cap in _NO_BF16_ISAS:
        return {"amx_bf16", "avx512_bf16"}
    return {"amx_bf16"} if cap in _NO_AMX_ISAS else set()


@functools.lru_cache(maxsize=1)
def cpu_bf16_flags() -> tuple[str, ...]:
    """The native-bf16 CPU flags of this machine (:data:`BF16_CPU_FLAGS` found in ``/proc/cpuinfo``).

    Where there is no ``/proc/cpuinfo`` (macOS, Windows), OpenVINO's view of the CPU answers instead
    (``BF16`` in its optimisation capabilities), when it is installed. The environment variable
    :data:`CPU_FLAGS_ENV` replaces the probe (a comma- or space-separated list; empty = no native bf16):
    the test suite runs every CPU kind's path through it (``pytest --cpu-kind amx|avx512bf16|none``), and
    a user can keep ``auto`` off bf16 with ``AERIALMTL_CPU_BF16_FLAGS=``. A ``ONEDNN_MAX_CPU_ISA`` cap below
    bf16 (or below AMX) takes those flags away: oneDNN then has no such kernels.
    """
    forced = os.environ.get(CPU_FLAGS_ENV)
    if forced is not None:
        return tuple(f for f in BF16_CPU_FLAGS if f in forced.replace(",", " ").split())
    if cpu_fields():
        return tuple(f for f in BF16_CPU_FLAGS if f in cpu_flags() - _capped_away())
    try:  # pragma: no cover - not Linux
        caps = openvino_core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
        return ("openvino:BF16",) if "BF16" in caps else ()
    except Exception:  # pragma: no cover
        return ()


_OPENVINO_CORE: Any = None
_OPENVINO_CORE_LOCK = threading.Lock()


def openvino_core() -> Any:
    """The process's one ``openvino.Core`` (created on first use, kept until the process ends).

    Every engine, export check and benchmark of aerialmtl compiles through this one: each ``Core`` loads its own
    CPU plugin, and the plugin points the calling thread's alternate signal stack at a buffer of its own
    (sized for AMX's signal frames), freeing that buffer when the ``Core`` goes. Cores created and dropped in
    another order than last-in-first-out (engines freed by the garbage collector) left the main thread's
    alternate stack on freed memory: the next signal handled there (a DataLoader worker's or a subprocess's
    SIGCHLD) was written into whatever used that memory (corrupted data) or killed the process with a
    segmentation fault (si_code SI_KERNEL), at random. One Core loads the plugin once.

    Raises:
        ImportError: OpenVINO is not installed.
    """
    global _OPENVINO_CORE
    with _OPENVINO_CORE_LOCK:
        if _OPENVINO_CORE is None:
            _OPENVINO_CORE = import_openvino().Core()
        return _OPENVINO_CORE


#: OpenVINO's usage-telemetry package, which ``import openvino`` loads (through ``openvino.tools.ovc``) when it is
#: installed: it sends an event to Google Analytics from a forked copy of the process and counts uses in
#: ``~/intel`` on every import, unless a consent file says no.
OPENVINO_TELEMETRY = "openvino_telemetry"


def import_openvino() -> ModuleType:
    """``import openvino``, the one place aerialmtl does it, without OpenVINO's usage telemetry.

    The first import of OpenVINO in a process loads its converter, which reports the import to Google Analytics
    (a forked copy of the process posts it, and waits for a timeout where there is no network) and writes
    ``~/intel/openvino_ga_cid`` and a use counter, unless the user opted out with OpenVINO's own tool. aerialmtl
    makes no network call and writes nothing but its outputs and its caches, so the telemetry package is hidden
    while OpenVINO is first imported: its converter then binds its no-op stand-in (as when the package is not
    installed) and keeps it for the life of the process. A process that imported OpenVINO or its telemetry
    before is left as it is.

    Raises:
        ImportError: OpenVINO is not installed.
    """
    if "openvino" not in sys.modules and OPENVINO_TELEMETRY not in sys.modules:
        sys.modules[OPENVINO_TELEMETRY] = None  # type: ignore[assignment]  # `import` of it raises ImportError
        try:
            import openvino  # noqa: F401
        finally:
            if sys.modules.get(OPENVINO_TELEMETRY, 0) is None:
                del sys.modules[OPENVINO_TELEMETRY]
    import openvino  # loaded above, or already by the process

    module: ModuleType = openvino
    return module


def cpu_has_amx() -> bool:
    """Whether the CPU has AMX-BF16 tiles (torch's own bf16 convolutions are fast only with them)."""
    return "amx_bf16" in cpu_bf16_flags()


def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` computes bf16 natively (the one bf16 check of the package)."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if device.type == "cpu":
        return bool(cpu_bf16_flags())
    return False


def resolve_precision(precision: str, device: torch.device, *, cpu_bf16: bool = False) -> Resolved:
    """``auto`` → ``bf16`` where the device computes it natively and it pays there, else ``fp32``.

    Args:
        precision: ``auto``, ``bf16`` or ``fp32``.
        device: where the model runs.
        cpu_bf16: whether the caller's CPU code path is faster in bf16 on a CPU with native bf16 (the
            OpenVINO engine is; torch's eager convolutions without AMX are not, bench/RESULTS.md). CUDA
            GPUs with bf16 always take it under ``auto``.

    Raises:
        InputError: another value.
    """
    if precision == "auto":
        if device.type == "cuda":
            return "bf16" if native_bf16(device) else "fp32"
        return "bf16" if cpu_bf16 and native_bf16(device) else "fp32"
    match precision:
        case "bf16" | "fp32":
            return precision
    raise InputError(f"‹precision={precision}› is not supported; use auto, bf16 or fp32", param="precision")


def autocast(device: torch.device, precision: str) -> contextlib.AbstractContextManager[Any]:
    """bf16 autocast on ``device`` for ``precision == "bf16"``, else nothing."""
    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


# ---- CPU threads --------------------------------------------------------------------------------
@dataclass(frozen=True)
class CpuThreads:
    """The inference threads of a process and their split into engine streams.

    Attributes:
        threads: threads computing the model (all streams together; torch's intra-op threads).
        streams: independent inference streams (OpenVINO ``NUM_STREAMS``), each running its own window
            or MC sample on ``threads // streams`` threads. Several narrow streams instead of one wide one
            keep a CPU shared with other processes busy: a wide stream splits every layer over all its
            threads and waits for the slowest, so one descheduled thread stalls all (bench/RESULTS.md,
            predict end to end).
        source: where ``threads`` came from: ``option``, ``env`` (:data:`THREADS_ENV`) or ``auto``.
    """

    threads: int
    streams: int
    source: str = "auto"

    def as_dict(self) -> dict[str, Any]:
        """What ``prediction.json`` records."""
        return {"threads": self.threads, "streams": self.streams, "source": self.source}


def _threads_value(value: int | str, param: str) -> int | None:
    """A positive thread count, or ``None`` for ``auto``."""
    number: int | None = None
    if isinstance(value, str):
        text = value.strip().lower()
        if text == "auto":
            return None
        number = int(text) if text.isdigit() else None
    elif isinstance(value, int) and not isinstance(value, bool):
        number = value
    if number is None or number < 1:
        where = f"the environment variable {THREADS_ENV}" if param == THREADS_ENV else f"‹{param}›"
        raise InputError(f"{where} must be a positive number of threads or 'auto', got {value!r}; "
                         "pass e.g. 2, or auto", param=None if param == THREADS_ENV else param)
    return number


def resolve_threads(threads: int | str | None = "auto") -> CpuThreads:
    """The inference threads of this process: ``threads`` (an option), else :data:`THREADS_ENV`, else
    torch's own count (``torch.get_num_threads()``: the cores this process may run on, or
    ``OMP_NUM_THREADS`` as torchrun sets it); a number given beyond :func:`usable_cpus` is that count, with one
    warning; split into ``min(threads, MAX_STREAMS)`` streams.

    Raises:
        InputError: a value that is not a positive number or ``auto`` (naming the option or variable).
    """
    n = _threads_value(threads if threads is not None else "auto", "threads")
    source = "option"
    if n is None:
        env = os.environ.get(THREADS_ENV, "").strip()
        n = _threads_value(env, THREADS_ENV) if env else None
        source = "env"
    if n is None:
        n, source = max(1, torch.get_num_threads()), "auto"
    cpus = usable_cpus()
    if source != "auto" and n > cpus:  # more threads than CPUs only wait on each other; a million cannot start
        where = f"{THREADS_ENV}={n}" if source == "env" else f"--threads {n}"
        warn_once(f"{where} is more than the {cpus} CPU(s) this process may use; using {cpus} thread(s)")
        n = cpus
    return CpuThreads(n, min(n, MAX_STREAMS), source)


# ---- compile ------------------------------------------------------------------------------------
class CompileFallback:
    """``torch.compile`` of methods of ``module``, each falling back to the eager method if it fails.

    Compilation errors surface at the first call; the first one warns once (``what`` names the caller)
    and every method runs eagerly from then on.
    """

    def __init__(self, module: nn.Module, what: str = "the model") -> None:
        self.module = module
        self.what = what
        self._calls: dict[str, Callable[..., Any]] = {}
        self.failed = False

    def __call__(self, name: str, *args: Any) -> Any:
        """Call method ``name`` of the module, compiled where it can be."""
        eager = getattr(self.module, name)
        if self.failed:
            return eager(*args)
        fn = self._calls.get(name)
        try:
            if fn is None:
                fn = torch.compile(eager)
                self._calls[name] = fn
            return fn(*args)
        except Exception as exc:
            if isinstance(exc, AerialMTLError):  # our own checks (input shapes...) are not compile failures
                raise
            self.failed = True
            _warn_compile_failed(exc, self.what)
            return eager(*args)


def _warn_compile_failed(exc: BaseException, what: str = "the model") -> None:
    """The one warning when ``torch.compile`` cannot be used."""
    why = cause(exc)
    warnings.warn(f"compile: torch.compile failed, torch.compile is not available here ({why}); running {what} "
                  "without it", UserWarning, stacklevel=3)


# ---- torchrun -----------------------------------------------------------------------------------
T = TypeVar("T")


@dataclass
class Torchrun:
    """This process's place in a ``torchrun`` job (``rank`` 0 of 1 outside torchrun) and the collectives
    that training and prediction use; every collective is a no-op for one process.

    Attributes:
        rank: global rank (0 for one process).
        world: number of processes.
        local_rank: rank on this machine (selects the GPU).
        device: the device of this process (set by :meth:`join`; the CPU before).
        owns_group: whether :meth:`leave` destroys the process group (:meth:`join` created it).
    """

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    owns_group: bool = False

    @classmethod
    def from_env(cls) -> Torchrun:
        """``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` as torchrun sets them."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        return cls(int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0")))

    @classmethod
    def start(cls, device: str, timeout: _dt.timedelta, error: type[AerialMTLError] = InputError) -> Torchrun:
        """The context of this process from torchrun's environment, its device resolved and the group joined.

        Args:
            device: ``auto``, ``cpu`` or ``cuda`` (:meth:`resolve_device`).
            timeout: how long a collective waits for a peer (:data:`COLLECTIVE_TIMEOUT`, :data:`SHARE_TIMEOUT`).
            error: the error type of a bad device (the trainer passes ConfigError).
        """
        env = cls.from_env()
        env.join(env.resolve_device(device, error), timeout)
        return env

    @property
    def distributed(self) -> bool:
        """Whether there are several processes."""
        return self.world > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes shared files and prints."""
        return self.rank == 0

    def resolve_device(self, device: str, error: type[AerialMTLError] = InputError) -> torch.device:
        """The device of this process (:func:`resolve_device`); on CUDA ``cuda:LOCAL_RANK``, made current.

        Raises:
            ``error``: more processes on this machine than GPUs (or a device error).
        """
        dev = resolve_device(device, self.local_rank, error)
        if self.distributed and dev.type == "cuda":
            if self.local_rank >= torch.cuda.device_count():
                raise error(
                    f"device: process {self.local_rank} of this machine needs cuda:{self.local_rank} but only "
                    f"{torch.cuda.device_count()} GPU(s) are visible; start at most that many processes per machine")
            if dev.index is None:
                dev = torch.device("cuda", self.local_rank)
            torch.cuda.set_device(dev)
        return dev

    def join(self, device: torch.device, timeout: _dt.timedelta) -> None:
        """Take ``device`` and join the process group (NCCL on CUDA, gloo otherwise) if there is none yet."""
        self.device = torch.device(device)
        if self.distributed and not dist.is_initialized():
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo", timeout=timeout)
            self.owns_group = True

    def leave(self) -> None:
        """Destroy the process group if :meth:`join` created it."""
        if self.owns_group and dist.is_initialized():
            dist.destroy_process_group()
        self.owns_group = False

    # ---- collectives (no-ops for one process) -------------------------------------------------------
    def barrier(self) -> None:
        """Wait until every rank is here."""
        if self.distributed:
            _collective(dist.barrier)

    def all_reduce_sum(self, tensor: torch.Tensor) -> torch.Tensor:
        """Sum ``tensor`` over ranks, in place (identical on every rank afterwards); returns it.

        A CPU tensor in a CUDA (nccl) run travels through the GPU and comes back.
        """
        if self.distributed:
            comm = self._comm_device()
            work = tensor if tensor.device == comm else tensor.to(comm)
            _collective(dist.all_reduce, work, op=dist.ReduceOp.SUM)
            if work is not tensor:
                tensor.copy_(work)
        return tensor

    def any(self, flag: bool) -> bool:
        """True on every rank when ``flag`` is true on at least one."""
        if not self.distributed:
            return flag
        t = torch.tensor([1.0 if flag else 0.0], device=self._comm_device())
        return bool(self.all_reduce_sum(t).item() > 0)

    def gather(self, obj: Any) -> list[Any]:
        """Every rank's ``obj``, in rank order, on every rank (also a barrier)."""
        if not self.distributed:
            return [obj]
        out: list[Any] = [None] * self.world
        _collective(dist.all_gather_object, out, obj)
        return out

    def broadcast(self, obj: T) -> T:
        """Rank 0's ``obj`` on every rank."""
        if not self.distributed:
            return obj
        box = [obj]
        _collective(dist.broadcast_object_list, box, src=0)
        return box[0]

    def main_first(self, fn: Callable[[], T]) -> T | None:
        """Run ``fn`` on rank 0; if it raises, every rank raises the same error (no rank is left waiting).

        Returns:
            ``fn``'s result on rank 0, ``None`` on the other ranks.
        """
        result: T | None = None
        error: BaseException | None = None
        if self.is_main:
            try:
                result = fn()
            except (AerialMTLError, OSError) as exc:
                error = exc
        error = self.broadcast(error)
        if error is not None:
            raise error
        return result

    def _comm_device(self) -> torch.device:
        return self.device if self.device.type == "cuda" else torch.device("cpu")


def peer_failure(exc: BaseException) -> PeerFailure:
    """The :class:`~aerialmtl.errors.PeerFailure` of a collective that failed because a peer is gone."""
    why = cause(exc)
    return PeerFailure(f"another process of this multi-process run failed or was stopped ({why}); its own message "
                       "or torchrun's summary says why. The last checkpoint in the run folder is whole: continue "
                       "with ‹resume=True›")


def is_peer_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a collective failing because another process is gone (gloo/nccl wording)."""
    if isinstance(exc, (dist.DistBackendError, dist.DistNetworkError)):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and any(
        s in text for s in ("Connection reset", "Connection closed", "Broken pipe", "gloo", "NCCL", "by peer"))


def _collective(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Call a torch.distributed collective; a broken peer becomes :class:`~aerialmtl.errors.PeerFailure`."""
    try:
        return fn(*args, **kwargs)
    except RuntimeError as exc:
        if is_peer_error(exc):
            raise peer_failure(exc) from exc
        raise


# ---- GDAL ---------------------------------------------------------------------------------------
def gdal_env(command: Literal["tile", "buildings", "predict"], **options: Any) -> rasterio.Env:
    """GDAL settings while ``command`` streams rasters (the one place that sets GDAL's block cache).

    Args:
        command: whose block cache: :data:`GDAL_CACHE_BYTES` (bytes, as ``rasterio.Env`` passes them to
            GDAL); a ``GDAL_CACHEMAX`` environment variable wins.
        options: other GDAL configuration options for the block (e.g. ``GDAL_TIFF_INTERNAL_MASK=True``).
    """
    if "GDAL_CACHEMAX" not in os.environ:  # a user's own setting wins
        options["GDAL_CACHEMAX"] = GDAL_CACHE_BYTES[command]
    return rasterio.Env(**options)


__all__ = ["BF16_CPU_FLAGS", "COLLECTIVE_TIMEOUT", "CPU_FLAGS_ENV", "MAX_STREAMS", "SHARE_TIMEOUT", "THREADS_ENV",
           "CompileFallback", "CpuThreads", "GDAL_CACHE_BYTES", "Precision", "Resolved", "Torchrun", "autocast",
           "cpu_bf16_flags", "cpu_has_amx", "gdal_env", "is_peer_error", "native_bf16", "openvino_core", "peer_failure",
           "resolve_device", "resolve_precision", "resolve_threads", "usable_cpus"]
