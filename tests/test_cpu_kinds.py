"""The CPU capability probe can be replaced (AERIALMTL_CPU_BF16_FLAGS, ``pytest --cpu-kind``), and ``auto`` then
chooses for each kind of CPU what it chooses on that CPU: bf16 on OpenVINO with AVX-512-BF16 or AMX, bf16 on
torch only with AMX, fp32 without native bf16."""

from __future__ import annotations

import pytest
import torch

from aerialmtl import runtime


@pytest.mark.parametrize(("flags", "openvino", "torch_engine"), [
    ("amx_bf16,avx512_bf16", "bf16", "bf16"),
    ("avx512_bf16", "bf16", "fp32"),
    ("", "fp32", "fp32"),
])
def test_auto_precision_per_cpu_kind(monkeypatch: pytest.MonkeyPatch, flags: str, openvino: str,
                                     torch_engine: str) -> None:
    monkeypatch.setenv(runtime.CPU_FLAGS_ENV, flags)
    runtime.cpu_bf16_flags.cache_clear()
    try:
        cpu = torch.device("cpu")
        assert runtime.resolve_precision("auto", cpu, cpu_bf16=True) == openvino
        assert runtime.resolve_precision("auto", cpu, cpu_bf16=runtime.cpu_has_amx()) == torch_engine
        assert runtime.resolve_precision("fp32", cpu, cpu_bf16=True) == "fp32"  # an explicit choice stays
        from conftest import tiny_d3net

        from aerialmtl.inference.predict import Predictor

        pytest.importorskip("openvino")
        assert Predictor(tiny_d3net(), mc=1).precision == openvino
        assert Predictor(tiny_d3net(), mc=1, engine="torch").precision == torch_engine
    finally:
        monkeypatch.undo()
        runtime.cpu_bf16_flags.cache_clear()
