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
and says where, when and at what load it measured.

:func:`choose_engine` is what prediction calls, once per job (:class:`~aerialmtl.inference.model.Predictor`):
an engine named is checked and run as asked (one warning per process where the table measured another one
faster); ``auto`` is :func:`auto_engine`, a pure function of the job (:class:`Job`: its size, MC samples, device
and which engine caches are warm), the CPU's kind, the engines that can run the model (each declares, in its
:class:`~aerialmtl.inference.engines.base.EngineSpec`, its expected speed where the table has no measurement
and what compiling costs it) and the table's entry for the kind. It weighs the compilation of a cold cache against
the job on every kind, measured or not: a job too small to earn the compilation back runs on an engine that
compiles nothing. The choice comes with its reason, which ``prediction.json`` records (``engine_choice``).

The probe can be replaced: :data:`CPU_KIND_ENV` names a kind outright (tests: ``pytest --cpu-kind``), and the
emulation of a smaller CPU caps it: ``ONEDNN_MAX_CPU_ISA=AVX2`` (which oneDNN, inside torch and OpenVINO,
obeys) makes the kind ``avx2``.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml

from aerialmtl.cpuinfo import cpu_flags
from aerialmtl.errors import ConfigError
from aerialmtl.inference.engines.names import ENGINE_MODULES, FALLBACK

if TYPE_CHECKING:  # pragma: no cover
    import torch
    from torch import nn

    from aerialmtl.inference.engines.base import EngineSpec

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
#: The torch engine's ``channels_last``, or the name of an engine that picks its own layouts.
Layout = str


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

    engine: str
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
    engines = "|".join(ENGINE_MODULES)
    if entry.engine not in ENGINE_MODULES or entry.precision not in ("fp32", "bf16") \
            or entry.layout not in ("channels_last", *ENGINE_MODULES):
        raise ConfigError(f"{source}: kinds.{kind} chooses {entry.engine}/{entry.precision}/{entry.layout}; "
                          f"use engine {engines}, precision fp32|bf16, layout channels_last|{engines}, or rewrite "
                          "it with `aerialmtl bench --write-table`")
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
        engine: a name of the engine registry; precision: ``fp32`` or ``bf16``; layout: see :class:`KindEntry`.
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


@dataclass(frozen=True)
class Job:
    """What ``auto`` weighs of a job (:func:`auto_engine`).

    Attributes:
        device: the device type (``cpu``, ``cuda``, ``mps``).
        work_mpx: the job's window megapixels (all its inputs, once); ``None`` while the job is not known (a
            :class:`~aerialmtl.inference.model.Predictor` used without a job): then no compilation is weighed.
        passes: model passes per window (MC samples × TTA views).
        warm: the engines whose caches hold every graph the job runs; the others compile first.
    """

    device: str = "cpu"
    work_mpx: float | None = None
    passes: int = 1
    warm: frozenset[str] = frozenset()

    @property
    def graphs(self) -> int:
        """Graphs an engine compiles for one window shape: the forward pass at one pass, else encoder and decoder."""
        return 1 if self.passes == 1 else 2


def _measured(name: str, entry: KindEntry) -> bool:
    """Whether the table's entry measured engine ``name`` (the reference engine always is: speeds are over it)."""
    return name in (entry.engine, FALLBACK) or any(k.startswith(f"{name}/") for k in entry.model_alone_mpx_s)


def _speedup(spec: EngineSpec, entry: KindEntry | None) -> float:
    """Engine ``spec``'s expected end-to-end speed over the reference (the torch engine at fp32) on a CPU of
    ``entry``'s kind: the table's where it measured the engine, else what the engine declares.

    The table's winner runs at its measured speed-up; an engine it measured and did not choose at most as fast
    (its model-alone speed at fp32 over the reference's, the reference 1.0): the bench chose the fastest.
    """
    if entry is None or not _measured(spec.name, entry):
        return spec.speedup
    best = entry.speedup or spec.speedup
    if spec.name == entry.engine:
        return best
    alone = entry.model_alone_mpx_s
    ref, own = alone.get(f"{FALLBACK}/fp32"), alone.get(f"{spec.name}/fp32")
    ratio = own / ref if spec.name != FALLBACK and own and ref else 1.0
    return min(ratio, best)


def auto_engine(job: Job, kind: CpuKind | None, specs: Sequence[EngineSpec], entry: KindEntry | None
                ) -> tuple[str, str]:
    """The engine ``--engine auto`` runs ``job`` on, and why: the one place ``auto`` is decided.

    A pure function of the job, the CPU's kind, the engines that can run the model there (``specs``, in the
    registry's order) and the table's entry for the kind. Off the CPU (``kind`` ``None``), the first of ``specs``.
    On a CPU, each engine is expected to take ``work / speed-up + graphs × compile_mpx`` (:func:`_speedup`; the
    compilation only where its cache is cold and the job known) in the reference engine's window megapixels; the
    quickest runs it, ties going to the table's winner, then to the registry's order.

    Returns:
        ``(engine name, reason)``.
    """
    if not specs:
        raise ValueError("auto_engine needs at least one engine that can run the model")
    if job.device != "cpu" or kind is None:
        return specs[0].name, f"{job.device}: the {specs[0].label} engine, bf16 where the GPU has it"
    speed = {s.name: _speedup(s, entry) for s in specs}
    work = 1.0 if job.work_mpx is None else job.work_mpx * max(1, job.passes)
    cold = {s.name: 0.0 if job.work_mpx is None or s.name in job.warm else job.graphs * s.compile_mpx for s in specs}
    winner = entry.engine if entry is not None else None

    def rank(i: int, warm: bool) -> tuple[float, bool, int]:
        name = specs[i].name
        return work / max(speed[name], 1e-9) + (0.0 if warm else cold[name]), name != winner, i

    chosen = specs[min(range(len(specs)), key=lambda i: rank(i, False))].name
    fastest = specs[min(range(len(specs)), key=lambda i: rank(i, True))]
    if fastest.name != chosen:
        return chosen, (f"auto on a CPU of kind {kind}, {fastest.label}'s cache cold for this model and window: "
                        f"{work:.3g} window Mpx run sooner on {chosen} than after compiling ({fastest.compile_mpx:g} "
                        f"Mpx per graph) at {speed[fastest.name]:.2f}× torch")
    return chosen, _auto_reason(kind, entry, chosen, speed)


def _auto_reason(kind: CpuKind, entry: KindEntry | None, chosen: str, speed: dict[str, float]) -> str:
    """Why ``auto`` runs ``chosen`` on a CPU of ``kind`` when no compilation decided."""
    speeds = ", ".join(f"{name} {v:.2f}×" for name, v in speed.items())
    if entry is None:
        return (f"no measurement for CPU kind {kind} in the table: {chosen} fastest by the engines' declared "
                f"speeds over torch fp32 ({speeds}), bf16 where the CPU has it natively")
    if chosen == entry.engine:
        ratio = f", {entry.speedup:.2f}× torch fp32" if entry.speedup else ""  # `measured` says of what
        return (f"auto on a CPU of kind {kind}: {entry.engine} {entry.precision} measured fastest within "
                f"the tolerances{ratio} ({entry.measured})")
    if entry.engine not in speed:
        return f"the table's {entry.engine} cannot run this model here; {chosen} instead"
    return (f"auto on a CPU of kind {kind}: {chosen} declares more speed than the table's {entry.engine} measured "
            f"({speeds}; {entry.measured})")


_warned: set[tuple[str, str]] = set()


def _warn_slower(kind: CpuKind, entry: KindEntry, engine: str, asked: str) -> None:
    """One warning per process and kind: an explicit engine where the table measured another one faster."""
    if (kind, asked) in _warned:
        return
    _warned.add((kind, asked))
    speeds = ", ".join(f"{k} {v:.3g}" for k, v in sorted(entry.model_alone_mpx_s.items()))
    warnings.warn(f"‹engine={engine}› runs slower than the {entry.engine} engine on this kind of CPU ({kind}: "
                  f"measured {speeds} Mpx/s for the model alone; {entry.measured}); ‹engine=auto› picks "
                  f"{entry.engine} {entry.precision} here", UserWarning, stacklevel=4)


def _precision(spec: EngineSpec, precision: str, device: torch.device, entry: KindEntry | None,
               auto: bool) -> Literal["fp32", "bf16"]:
    """The precision engine ``spec`` runs at for the ``precision`` option: the table's for its winner under
    ``auto`` (never emulated bf16), else :func:`aerialmtl.runtime.resolve_precision` with the engine's bf16 rule.
    """
    from aerialmtl import runtime

    if device.type != "cpu":
        return runtime.resolve_precision(precision, device)
    if auto and entry is not None and spec.name == entry.engine and precision == "auto":
        # the table's kind and the bf16 probe may disagree (an override): never emulated bf16
        return entry.precision if entry.precision != "bf16" or runtime.native_bf16(device) else "fp32"
    return runtime.resolve_precision(precision, device, cpu_bf16=not spec.bf16_needs_amx or runtime.cpu_has_amx())


def choose_engine(engine: str, precision: str, device: torch.device, model: nn.Module | Any,
                  table: dict[CpuKind, KindEntry] | None = None, *, job: Job | None = None,
                  cached: Callable[[str, Literal["fp32", "bf16"]], bool] | None = None) -> EngineChoice:
    """Resolve the ``engine`` and ``precision`` options of a prediction (see the module docstring).

    Args:
        engine: ``auto`` (:func:`auto_engine`, once, with ``job``) or a name of the registry (checked by
            :func:`~aerialmtl.inference.engines.resolve_engine`, which also says why it cannot run).
        precision: ``auto``, ``bf16`` or ``fp32``.
        device: where the model runs.
        model: the model (or its checkpoint record): some engines run some models only.
        table: kind → entry; default :func:`shipped_table`.
        job: the job's size (default: not known yet; its ``warm`` is filled here by asking ``cached``).
        cached: ``(engine, precision)`` → whether that engine's cache holds every graph of the job; only engines
            that compile are asked, and only for a known job (default: none is).

    Raises:
        InputError: an unknown engine or precision, or an engine asked for where it cannot run.
    """
    # torch (runtime) and the engines load when an engine is chosen: reading the table (cli bench, the tests'
    # CPU kind) stays light
    from aerialmtl import runtime
    from aerialmtl.inference.engines import ENGINES, engine_spec, resolve_engine, usable_engines

    asked = f"engine={engine}, precision={precision}"
    runtime.resolve_precision(precision, device)  # a bad value fails here, named
    kind = cpu_kind() if device.type == "cpu" else None
    entry = None if kind is None else (shipped_table() if table is None else table).get(kind)
    if engine != "auto":
        spec = engine_spec(resolve_engine(engine, device, model))
        prec, reason = _precision(spec, precision, device, entry, False), "asked for"
        if kind is None:
            reason = f"{device.type}: the torch engine, bf16 where the GPU has it"
        if entry is not None and entry.engine != engine and engine != FALLBACK and _measured(engine, entry):
            _warn_slower(kind, entry, engine, asked)  # type: ignore[arg-type]  # kind is set with entry
            reason = f"asked for; measured slower than {entry.engine} {entry.precision} on kind {kind}"
        return EngineChoice(engine, prec, layout_of(spec), asked, kind, reason)
    specs = usable_engines(device, model)
    job = job if job is not None else Job(device.type)
    precisions = {s.name: _precision(s, precision, device, entry, True) for s in specs}
    if job.work_mpx is not None and cached is not None:
        job = dataclasses.replace(job, warm=frozenset(s.name for s in specs if s.compile_mpx > 0
                                                      and cached(s.name, precisions[s.name])))
    name, reason = auto_engine(job, kind, specs, entry)
    spec = ENGINES[name]
    return EngineChoice(name, precisions[name], layout_of(spec), asked, kind, reason)


def layout_of(spec: EngineSpec) -> Layout:
    """What :attr:`EngineChoice.layout` records of an engine: its own layout, or its name where it picks its own."""
    return spec.layout if spec.layout is not None else spec.name


__all__ = ["CPU_KINDS", "CPU_KIND_ENV", "TABLE_RESOURCE", "TOLERANCES", "CpuKind", "EngineChoice", "Job", "KindEntry",
           "auto_engine", "choose_engine", "cpu_kind", "kind_of", "layout_of", "read_table",
           "shipped_table"]
