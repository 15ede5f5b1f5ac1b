"""What ``--engine auto`` runs on this CPU: the engine × precision × layout measured fastest on its kind of CPU.

The CPU's **kind** (:func:`cpu_kind`) is what decides which kernels an engine can use:

==================  ============================================================================
kind                meaning (``/proc/cpuinfo`` flags)
==================  ============================================================================
``amx``             AMX-BF16 tiles (Intel Sapphire Rapids and later)
``avx512_bf16``     AVX-512 with BF16 dot products, no AMX (AMD Zen 4 and later, Intel Cooper Lake)
``avx512``          AVX-512 without BF16 (Intel Skylake-SP to Ice Lake)
``avx2``            AVX2 without AVX-512 (most laptops and desktops, AMD Zen 1-3, many cloud VMs)
``none``            none of these (arm64, very old x86): no measurement, torch's defaults
==================  ============================================================================

The **table** (``aerialmtl/resources/engine_choice.yaml``) maps each kind to the engine, precision and layout
that ran the full D3-Net fastest end to end while keeping its outputs within :data:`TOLERANCES` of torch fp32;
``aerialmtl bench --write-table`` writes it from a run on the CPU at hand (one kind per run; the others are kept)
and says where, when and at what load it measured. A kind without a measurement keeps the rule that held
before the table (OpenVINO where it is installed, bf16 where the CPU has it natively), and says so.

:func:`choose_engine` is what prediction calls: the registry's resolver
(:func:`~aerialmtl.inference.engines.registry.resolve_engine`, the one owner of ``auto``: the first registered
engine that can run the model here) says what can run, and this table, where it has the CPU's kind, picks
among those what ran fastest. It returns the choice with its reason, which ``prediction.json`` records
(``engine_choice``). An explicit ``--engine openvino`` on a kind where
it was measured slower than torch runs as asked, with one warning per process.

The probe can be replaced: :data:`CPU_KIND_ENV` names a kind outright (tests: ``pytest --cpu-kind``), and the
emulation of a smaller CPU caps it: ``ONEDNN_MAX_CPU_ISA=AVX2`` (which oneDNN, inside torch and OpenVINO,
obeys) makes the kind ``avx2``.
"""

from __future__ import annotations

import functools
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml

from aerialmtl.cpuinfo import cpu_flags
from aerialmtl.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    import torch
    from torch import nn

CpuKind = Literal["amx", "avx512_bf16", "avx512", "avx2", "none"]
#: The kinds, fastest first.
CPU_KINDS: tuple[CpuKind, ...] = ("amx", "avx512_bf16", "avx512", "avx2", "none")
#: Environment variable naming the CPU kind outright (one of :data:`CPU_KINDS`), instead of the probe.
CPU_KIND_ENV = "AERIALMTL_CPU_KIND"
#: ``ONEDNN_MAX_CPU_ISA`` values (upper case) → the kind they cap the CPU at.
_ISA_CAPS: dict[str, CpuKind] = {
    "SSE41": "none", "AVX": "none", "AVX2": "avx2", "AVX2_VNNI": "avx2", "AVX2_VNNI_2": "avx2",
    "AVX512_CORE": "avx512", "AVX512_CORE_VNNI": "avx512", "AVX512_CORE_BF16": "avx512_bf16",
    "AVX10_1_512": "avx512_bf16", "AVX512_CORE_FP16": "avx512_bf16",
}
#: How close to torch fp32 each precision must stay to be chosen by ``auto`` (the bench's model-alone maps):
#: the mean absolute height difference in metres (``height_mae_m``) or relative to the mean |height|
#: (``height_rel_mae``), and the share of pixels whose class agrees. fp32: float rounding; bf16: the bounds the
#: engine-matrix tests state for bf16 (tests/test_engine_matrix.py: 8-bit mantissa through an untrained network);
#: int8: issue 39's bar for adopting post-training quantisation (0.05 m, 99.5 %).
TOLERANCES: dict[str, dict[str, float]] = {
    "fp32": {"height_mae_m": 1e-3, "class_agreement": 0.999},
    "bf16": {"height_rel_mae": 0.1, "class_agreement": 0.9},
    "int8": {"height_mae_m": 0.05, "class_agreement": 0.995},
}
#: The table shipped with the package.
TABLE_RESOURCE = "engine_choice.yaml"
Layout = Literal["channels_last", "openvino"]


def _flags() -> set[str]:
    return set(cpu_flags())


def kind_of(flags: set[str] | frozenset[str]) -> CpuKind:
    """The kind of a CPU with these ``/proc/cpuinfo`` flags."""
    if "amx_bf16" in flags:
        return "amx"
    if "avx512_bf16" in flags:
        return "avx512_bf16"
    if "avx512f" in flags:
        return "avx512"
    if "avx2" in flags:
        return "avx2"
    return "none"


def _slower(a: CpuKind, b: CpuKind) -> CpuKind:
    return a if CPU_KINDS.index(a) >= CPU_KINDS.index(b) else b


@functools.lru_cache(maxsize=1)
def cpu_kind() -> CpuKind:
    """This CPU's kind (see the module docstring): :data:`CPU_KIND_ENV` if set, else the CPU's flags, capped by
    ``ONEDNN_MAX_CPU_ISA`` (an emulated smaller CPU) and by the bf16 probe's override
    (:data:`aerialmtl.runtime.CPU_FLAGS_ENV`, which ``pytest --cpu-kind`` sets).

    Raises:
        ConfigError: :data:`CPU_KIND_ENV` names no kind.
    """
    forced = os.environ.get(CPU_KIND_ENV, "").strip().lower()
    if forced:
        if forced not in CPU_KINDS:
            raise ConfigError(f"the environment variable {CPU_KIND_ENV}={forced!r} names no CPU kind; use one of "
                              f"{', '.join(CPU_KINDS)}, or unset it")
        return forced
    flags = _flags()
    bf16 = os.environ.get("AERIALMTL_CPU_BF16_FLAGS")  # runtime.CPU_FLAGS_ENV (not imported: it imports torch)
    if bf16 is not None:
        flags = (flags - {"amx_bf16", "avx512_bf16"}) | set(bf16.replace(",", " ").split())
        if flags & {"amx_bf16", "avx512_bf16"}:
            flags.add("avx512f")
    kind = kind_of(flags)
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA", "").strip().upper()
    if cap in _ISA_CAPS:
        kind = _slower(kind, _ISA_CAPS[cap])
    return kind


# ---- the table ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class KindEntry:
    """What was measured fastest on one CPU kind (one entry of the table).

    Attributes:
        engine, precision, layout: the choice (``layout``: the torch engine's ``channels_last``; OpenVINO
            picks its own blocked layouts, ``openvino``).
        speedup: end-to-end speed of the choice over ``--engine torch --precision fp32`` (full D3-Net, T = 1).
        measured: where and when: CPU, cores, load, date, and whether the kind was reached or emulated.
        model_alone_mpx_s: model-alone Mpx/s of each ``engine/precision`` measured (full D3-Net).
        accuracy: per ``engine/precision``, height MAE (m) and class agreement against torch fp32.
        notes: anything the choice depends on (e.g. why int8 was not adopted).
    """

    engine: Literal["torch", "openvino"]
    precision: Literal["fp32", "bf16"]
    layout: Layout
    speedup: float | None = None
    measured: str = ""
    model_alone_mpx_s: dict[str, float] = field(default_factory=dict)
    accuracy: dict[str, dict[str, float]] = field(default_factory=dict)
    notes: str = ""


def _entry(kind: str, raw: Any, source: str) -> KindEntry:
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: kinds.{kind} must be a mapping with engine, precision and layout; "
                          "rewrite it with `aerialmtl bench --write-table`")
    try:
        entry = KindEntry(**raw)
    except TypeError as exc:
        raise ConfigError(f"{source}: kinds.{kind}: {exc}; rewrite it with `aerialmtl bench --write-table`") from None
    if entry.engine not in ("torch", "openvino") or entry.precision not in ("fp32", "bf16") \
            or entry.layout not in ("channels_last", "openvino"):
        raise ConfigError(f"{source}: kinds.{kind} chooses {entry.engine}/{entry.precision}/{entry.layout}; "
                          "use engine torch|openvino, precision fp32|bf16, layout channels_last|openvino")
    return entry


def read_table(path: str | Path | None = None) -> dict[CpuKind, KindEntry]:
    """The table of ``path`` (default: the one shipped, :data:`TABLE_RESOURCE`): kind → :class:`KindEntry`.

    Raises:
        ConfigError: not a table of this format (the message names the file and the fix).
    """
    path = Path(path) if path is not None else Path(__file__).resolve().parents[1] / "resources" / TABLE_RESOURCE
    try:
        text, source = path.read_text(encoding="utf-8"), str(path)
    except OSError as exc:
        raise ConfigError(f"cannot read the engine-choice table {path}: {exc.strerror}; reinstall aerialmtl or "
                          "write it with `aerialmtl bench --write-table`") from None
    data = yaml.safe_load(text) or {}
    kinds = data.get("kinds") if isinstance(data, dict) else None
    if not isinstance(kinds, dict):
        raise ConfigError(f"{source} has no 'kinds' mapping; rewrite it with `aerialmtl bench --write-table`")
    unknown = sorted(set(kinds) - set(CPU_KINDS))
    if unknown:
        raise ConfigError(f"{source}: unknown CPU kinds {unknown}; use {', '.join(CPU_KINDS)}")
    return {k: _entry(k, v, source) for k, v in kinds.items() if v is not None}


@functools.lru_cache(maxsize=1)
def shipped_table() -> dict[CpuKind, KindEntry]:
    """The shipped table (:func:`read_table`), read once."""
    return read_table()


# ---- the choice --------------------------------------------------------------------------------
@dataclass(frozen=True)
class EngineChoice:
    """The engine and precision a prediction runs on, and why (``prediction.json``'s ``engine_choice``).

    Attributes:
        engine: a name of the engine registry (``torch``, ``openvino``); precision: ``fp32`` or ``bf16``;
            layout: see :class:`KindEntry`.
        asked: the ``engine``/``precision`` options as given; cpu_kind: :func:`cpu_kind` (``None`` off the CPU).
        reason: one sentence: which rule or measurement decided.
    """

    engine: str
    precision: Literal["fp32", "bf16"]
    layout: Layout
    asked: str
    cpu_kind: CpuKind | None
    reason: str

    def as_dict(self) -> dict[str, Any]:
        """What ``prediction.json`` records."""
        return asdict(self)


_warned: set[tuple[str, str]] = set()


def _warn_slower(kind: CpuKind, entry: KindEntry, asked: str) -> None:
    """One warning per process and kind: an explicit OpenVINO where torch was measured faster."""
    if (kind, asked) in _warned:
        return
    _warned.add((kind, asked))
    speeds = ", ".join(f"{k} {v:.3g}" for k, v in sorted(entry.model_alone_mpx_s.items()))
    warnings.warn(f"‹engine=openvino› runs slower than the torch engine on this kind of CPU ({kind}: measured "
                  f"{speeds} Mpx/s for the model alone; {entry.measured}); ‹engine=auto› picks "
                  f"{entry.engine} {entry.precision} here", UserWarning, stacklevel=3)


def choose_engine(engine: str, precision: str, device: torch.device, model: nn.Module | Any,
                  table: dict[CpuKind, KindEntry] | None = None) -> EngineChoice:
    """Resolve the ``engine`` and ``precision`` options of a prediction (see the module docstring).

    Args:
        engine: ``auto``, ``torch`` or ``openvino`` (checked by
            :func:`~aerialmtl.inference.engines.resolve_engine`, which also says why OpenVINO cannot run).
        precision: ``auto``, ``bf16`` or ``fp32``.
        device: where the model runs.
        model: the model (or its checkpoint record): OpenVINO converts D3-Nets only.
        table: kind → entry; default :func:`shipped_table`.

    Raises:
        InputError: an unknown engine or precision, or OpenVINO asked for where it cannot run.
    """
    # torch (runtime) and the engines load when an engine is chosen: reading the table (cli bench, the tests'
    # CPU kind) stays light
    from aerialmtl import runtime
    from aerialmtl.inference.engines import resolve_engine

    asked = f"engine={engine}, precision={precision}"
    runtime.resolve_precision(precision, device)  # a bad value fails here, named
    resolved = resolve_engine(engine, device, model)  # explicit choices checked; auto → openvino where it can run
    if device.type != "cpu":
        prec = runtime.resolve_precision(precision, device)
        return EngineChoice(resolved, prec, "channels_last", asked, None,
                            f"{device.type}: the torch engine, bf16 where the GPU has it")
    kind = cpu_kind()
    entry = (shipped_table() if table is None else table).get(kind)
    layout: Layout = "openvino" if resolved == "openvino" else "channels_last"
    if engine == "auto" and entry is not None and (resolved == "openvino" or entry.engine == "torch"):
        prec = entry.precision if precision == "auto" else runtime.resolve_precision(precision, device)
        if prec == "bf16" and precision == "auto" and not runtime.native_bf16(device):
            prec = "fp32"  # the table's kind and the bf16 probe disagree (an override): never emulated bf16
        ratio = f", {entry.speedup:.2f}× torch fp32" if entry.speedup else ""  # `measured` says of what
        return EngineChoice(entry.engine, prec, entry.layout, asked, kind,
                            f"auto on a CPU of kind {kind}: {entry.engine} {entry.precision} measured fastest within "
                            f"the tolerances{ratio} ({entry.measured})")
    prec = runtime.resolve_precision(precision, device,
                                     cpu_bf16=resolved == "openvino" or runtime.cpu_has_amx())
    if engine == "openvino" and entry is not None and entry.engine == "torch":
        _warn_slower(kind, entry, asked)
        return EngineChoice(resolved, prec, layout, asked, kind,
                            f"asked for; measured slower than {entry.engine} {entry.precision} on kind {kind}")
    if engine != "auto":
        return EngineChoice(resolved, prec, layout, asked, kind, "asked for")
    if entry is None:
        why = (f"no measurement for CPU kind {kind} in the table: OpenVINO where it can run, bf16 where the CPU "
               "has it natively (the rule before the table)")
    else:
        why = f"the table's {entry.engine} cannot run this model here; {resolved} instead"
    return EngineChoice(resolved, prec, layout, asked, kind, why)


# ---- a cold engine cache ----------------------------------------------------------------------
#: What converting and compiling the full D3-Net for one window shape costs, in window megapixels of the torch
#: engine (fp32) on the same CPU. Measured on an AVX2 AMD Zen 3 (issue 46): a first 2048² T = 1 predict (4.9 window
#: megapixels) ran 0.55× the torch engine, the second 1.69×, so the compilation took (1/0.55 − 1/1.69) ≈ 1.23
#: torch runs of that job ≈ 6 megapixels. Compilation and the torch engine both slow down with the CPU, so the
#: cost is kept in the torch engine's work rather than in seconds.
COMPILE_TORCH_MPX = 6.0


def cold_start_pays(work_mpx: float, speedup: float, graphs: int = 1,
                    compile_mpx: float = COMPILE_TORCH_MPX) -> bool:
    """Whether OpenVINO, converting and compiling ``graphs`` graphs first, finishes a job no later than the torch
    engine: ``work / speedup + graphs × compile ≤ work``, all in the torch engine's window megapixels.

    Args:
        work_mpx: the job's window megapixels times its model passes (MC samples, TTA views).
        speedup: OpenVINO's measured speed over the torch engine (the table's :attr:`KindEntry.speedup`).
        graphs: graphs compiled (the forward pass at T = 1; the encoder and the decoder at T > 1).
        compile_mpx: the cost of one graph's compilation (:data:`COMPILE_TORCH_MPX`).
    """
    return work_mpx / max(speedup, 1e-9) + graphs * compile_mpx <= work_mpx


def cold_cache_choice(choice: EngineChoice, precision: str, device: torch.device, work_mpx: float, samples: int,
                      warm: bool, table: dict[CpuKind, KindEntry] | None = None) -> EngineChoice:
    """``auto``'s choice for a job once its size and the engine cache are known: the table's OpenVINO, when the
    graphs the job runs are not compiled in the cache (``warm`` false) and :func:`cold_start_pays` says the torch
    engine finishes first, gives way to the torch engine (``precision``: as an explicit torch engine resolves it).
    Every other choice is returned as it is, as is a kind without a measured speedup (nothing to weigh).

    A job the torch engine takes leaves the cache cold; the first job large enough for compilation to pay (or one
    run with ``--engine openvino``) fills it, and the later jobs on this model and window shape take OpenVINO.

    Args:
        choice: :func:`choose_engine`'s choice.
        precision: the ``precision`` option as given.
        device: where the model runs.
        work_mpx: the job's window megapixels (all inputs), once.
        samples: model passes per window (MC samples × TTA views).
        warm: whether the cache holds the compiled graphs of every window shape of the job.
        table: kind → entry; default :func:`shipped_table`.
    """
    if not choice.asked.startswith("engine=auto") or choice.engine != "openvino" or warm or choice.cpu_kind is None:
        return choice
    entry = (shipped_table() if table is None else table).get(choice.cpu_kind)
    if entry is None or not entry.speedup or entry.engine != "openvino":
        return choice
    work = work_mpx * max(1, samples)
    if cold_start_pays(work, entry.speedup, 1 if samples == 1 else 2):
        return choice
    from aerialmtl import runtime  # torch: see choose_engine

    prec = runtime.resolve_precision(precision, device, cpu_bf16=runtime.cpu_has_amx())
    why = (f"auto on a CPU of kind {choice.cpu_kind}, OpenVINO's cache cold for this model and window: {work:.3g} "
           f"window Mpx run sooner on torch than after compiling ({COMPILE_TORCH_MPX:g} Mpx per graph) at "
           f"{entry.speedup:.2f}× torch")
    return EngineChoice("torch", prec, "channels_last", choice.asked, choice.cpu_kind, why)


__all__ = ["COMPILE_TORCH_MPX", "CPU_KINDS", "CPU_KIND_ENV", "TABLE_RESOURCE", "TOLERANCES", "CpuKind", "EngineChoice",
           "KindEntry", "choose_engine", "cold_cache_choice", "cold_start_pays", "cpu_kind", "kind_of", "read_table",
           "shipped_table"]
