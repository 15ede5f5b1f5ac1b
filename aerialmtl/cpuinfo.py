"""The CPU as Linux describes it: the fields of ``/proc/cpuinfo``, read in one place.

The engines' choices (:mod:`aerialmtl.runtime`'s bf16 probe, :mod:`aerialmtl.inference.engine_choice`'s CPU kind),
the benchmarks' machine line and a run's record of its machine all read the same first processor block. No torch
here: the light callers (the engine table, the test suite's CPU kind) stay light.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

#: Where Linux describes the CPU; absent on macOS and Windows.
PROC_CPUINFO = Path("/proc/cpuinfo")


@functools.lru_cache(maxsize=1)
def cpu_fields() -> dict[str, str]:
    """The first processor's fields (``"model name"``, ``"cpu family"``, ``"model"``, ``"flags"``, ...) as text,
    stripped; empty where there is no ``/proc/cpuinfo`` or it cannot be read. Read once per process.
    """
    try:
        text = PROC_CPUINFO.read_text(errors="replace")
    except OSError:
        return {}
    fields: dict[str, str] = {}
    for line in text.split("\n\n", 1)[0].splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    return fields


def cpu_flags() -> frozenset[str]:
    """The first processor's feature flags (``avx2``, ``avx512_bf16``, ``amx_bf16``, ...); empty off Linux."""
    return frozenset(cpu_fields().get("flags", "").split())


def cpu_name() -> str | None:
    """``"<model name> family F model M"`` of the first processor, or ``None`` off Linux."""
    f = cpu_fields()
    if "model name" not in f:
        return None
    parts = [f["model name"]]
    if "cpu family" in f:
        parts.append(f"family {f['cpu family']}")
    if "model" in f:
        parts.append(f"model {f['model']}")
    return " ".join(parts)


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity where the system says, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


__all__ = ["PROC_CPUINFO", "cpu_fields", "cpu_flags", "cpu_name", "usable_cpus"]
