"""The CPU capability probe can be replaced (AERIALMTL_CPU_BF16_FLAGS, AERIALMTL_CPU_KIND, ``pytest --cpu-kind``),
and ``auto`` then chooses for each kind of CPU what it chooses on that CPU: the measured table's engine and
precision where the kind was measured (aerialmtl/resources/engine_choice.yaml), else bf16 on OpenVINO with
AVX-512-BF16 or AMX; an explicit torch engine takes bf16 only with AMX, fp32 without native bf16."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from aerialmtl import runtime


@pytest.mark.parametrize(("flags", "kind", "openvino", "torch_engine"), [
    ("amx_bf16,avx512_bf16", "amx", "bf16", "bf16"),
    ("avx512_bf16", "avx512_bf16", "bf16", "fp32"),
    ("", "avx512", "fp32", "fp32"),
    ("", "avx2", "fp32", "fp32"),
])
def test_auto_precision_per_cpu_kind(monkeypatch: pytest.MonkeyPatch, flags: str, kind: str, openvino: str,
                                     torch_engine: str) -> None:
    from aerialmtl.inference import engine_choice

    monkeypatch.setenv(runtime.CPU_FLAGS_ENV, flags)
    monkeypatch.setenv(engine_choice.CPU_KIND_ENV, kind)
    runtime.cpu_bf16_flags.cache_clear()
    engine_choice.cpu_kind.cache_clear()
    try:
        cpu = torch.device("cpu")
        assert runtime.resolve_precision("auto", cpu, cpu_bf16=True) == openvino
        assert runtime.resolve_precision("auto", cpu, cpu_bf16=runtime.cpu_has_amx()) == torch_engine
        assert runtime.resolve_precision("fp32", cpu, cpu_bf16=True) == "fp32"  # an explicit choice stays
        from helpers.models import tiny_d3net

        from aerialmtl.inference.predict import Predictor

        pytest.importorskip("openvino")
        measured = engine_choice.shipped_table().get(kind)  # auto follows the table where the kind was measured
        auto = Predictor(tiny_d3net(), mc=1)
        if measured is None:
            assert (auto.engine, auto.precision) == ("openvino", openvino)
        else:
            assert (auto.engine, auto.precision) == (measured.engine, measured.precision)
        assert auto.choice.cpu_kind == kind
        assert Predictor(tiny_d3net(), mc=1, engine="torch").precision == torch_engine
    finally:
        monkeypatch.undo()
        runtime.cpu_bf16_flags.cache_clear()
        engine_choice.cpu_kind.cache_clear()


def test_the_cpu_is_read_from_the_first_processor_block_and_missing_is_empty(tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """One reader of /proc/cpuinfo for the engines' probes, the benchmarks and a run's machine record: the first
    processor's fields; no file (macOS, Windows) gives nothing rather than an error."""
    from aerialmtl import cpuinfo

    fake = tmp_path / "cpuinfo"
    fake.write_text("processor\t: 0\nmodel name\t: Test CPU 9000\ncpu family\t: 25\nmodel\t\t: 33\n"
                    "flags\t\t: fpu avx2 avx512_bf16\n\nprocessor\t: 1\nmodel name\t: Other\nflags\t\t: fpu\n")
    monkeypatch.setattr(cpuinfo, "PROC_CPUINFO", fake)
    cpuinfo.cpu_fields.cache_clear()
    try:
        assert cpuinfo.cpu_flags() == {"fpu", "avx2", "avx512_bf16"}
        assert cpuinfo.cpu_name() == "Test CPU 9000 family 25 model 33"
        monkeypatch.setattr(cpuinfo, "PROC_CPUINFO", tmp_path / "absent")
        cpuinfo.cpu_fields.cache_clear()
        assert cpuinfo.cpu_fields() == {} and cpuinfo.cpu_flags() == frozenset() and cpuinfo.cpu_name() is None
    finally:
        cpuinfo.cpu_fields.cache_clear()
