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
* **GDAL** — :func:`gdal_env`: a bounded block cache while rasters are streamed.
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
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import rasterio
import torch
from torch import nn

from aerialmtl.errors import AerialMTLError, InputError

Precision = Literal["auto", "bf16", "fp32"]
Resolved = Literal["bf16", "fp32"]

#: How long a training collective may wait for a peer before the run is declared hung (the ranks run
#: in step; cache builds are locked per file, not by collectives, so this only bounds a real hang).
COLLECTIVE_TIMEOUT = _dt.timedelta(minutes=30)
#: How long a prediction rank waits for the others at the end of its share (they may have hours of
#: work left: the shares are equal in pixels, not in time).
SHARE_TIMEOUT = _dt.timedelta(days=7)
#: GDAL block cache while streaming rasters (MB): it serves the windows being read (a few tiles each)
#: and the staging tiles being written; a larger cache only grows memory with the raster width. A
#: ``GDAL_CACHEMAX`` environment variable wins.
GDAL_CACHE_MB = 32
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
@functools.lru_cache(maxsize=1)
def cpu_bf16_flags() -> tuple[str, ...]:
    """The native-bf16 CPU flags of this machine (:data:`BF16_CPU_FLAGS` found in ``/proc/cpuinfo``).

    Where there is no ``/proc/cpuinfo`` (macOS, Windows), OpenVINO's view of the CPU answers instead
    (``BF16`` in its optimisation capabilities), when it is installed. The environment variable
    :data:`CPU_FLAGS_ENV` replaces the probe (a comma- or space-separated list; empty = no native bf16):
    the test suite runs every CPU kind's path through it (``pytest --cpu-kind amx|avx512bf16|none``), and
    a user can keep ``auto`` off bf16 with ``AERIALMTL_CPU_BF16_FLAGS=``.
    """
    forced = os.environ.get(CPU_FLAGS_ENV)
    if forced is not None:
        return tuple(f for f in BF16_CPU_FLAGS if f in forced.replace(",", " ").split())
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        flags: set[str] = set()
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.startswith("flags"):
                flags.update(line.split(":", 1)[-1].split())
                break
        return tuple(f for f in BF16_CPU_FLAGS if f in flags)
    try:  # pragma: no cover - not Linux
        import openvino as ov

        caps = ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
        return ("openvino:BF16",) if "BF16" in caps else ()
    except Exception:  # pragma: no cover
        return ()


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
    if precision not in ("bf16", "fp32"):
        raise InputError(f"‹precision={precision}› is not supported; use auto, bf16 or fp32", param="precision")
    return precision  # type: ignore[return-value]


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
    ``OMP_NUM_THREADS`` as torchrun sets it); split into ``min(threads, MAX_STREAMS)`` streams.

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
            warn_compile_failed(exc, self.what)
            return eager(*args)


def warn_compile_failed(exc: BaseException, what: str = "the model") -> None:
    """The one warning when ``torch.compile`` cannot be used."""
    why = " ".join(str(exc).split())[:200] or exc.__class__.__name__
    warnings.warn(f"compile: torch.compile failed, torch.compile is not available here ({why}); running {what} "
                  "without it", UserWarning, stacklevel=3)


# ---- torchrun -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Torchrun:
    """This process's place in a ``torchrun`` job (``rank`` 0 of 1 outside torchrun)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @classmethod
    def from_env(cls) -> Torchrun:
        """``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` as torchrun sets them."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        return cls(int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0")))

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def device(self, device: str, error: type[AerialMTLError] = InputError) -> torch.device:
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

    def join(self, device: torch.device, timeout: _dt.timedelta) -> bool:
        """Join the process group (NCCL on CUDA, gloo otherwise); returns whether this call created it."""
        import torch.distributed as dist

        if not self.distributed or dist.is_initialized():
            return False
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=timeout)
        return True

    @staticmethod
    def leave() -> None:
        """Destroy the process group if there is one."""
        import torch.distributed as dist

        if dist.is_initialized():
            dist.destroy_process_group()


# ---- GDAL ---------------------------------------------------------------------------------------
def gdal_env() -> rasterio.Env:
    """GDAL settings while streaming rasters: the block cache bounded to :data:`GDAL_CACHE_MB` unless
    the user set ``GDAL_CACHEMAX``."""
    return rasterio.Env() if "GDAL_CACHEMAX" in os.environ else rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB)


__all__ = ["BF16_CPU_FLAGS", "COLLECTIVE_TIMEOUT", "CPU_FLAGS_ENV", "MAX_STREAMS", "SHARE_TIMEOUT", "THREADS_ENV",
           "CompileFallback", "CpuThreads", "GDAL_CACHE_MB", "Precision", "Resolved", "Torchrun", "autocast",
           "cpu_bf16_flags", "cpu_has_amx", "gdal_env", "native_bf16", "resolve_device", "resolve_precision",
           "resolve_threads", "warn_compile_failed"]
