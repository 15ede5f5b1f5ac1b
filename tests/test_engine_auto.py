"""``--engine auto`` is decided once, by one pure function (aerialmtl.inference.engine_choice.auto_engine) of the job,
the CPU kind and what the engines' specs declare: it weighs a cold cache's compilation on every CPU kind (the table's
and the unmeasured ones: an Intel Ice Lake, AVX-512 without BF16, paid OpenVINO's compilation for a 2048² T = 1 job),
an engine registered with the best declared speed is chosen, and a predictor builds one runner."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import fake_engine
from helpers.models import tiny_d3net
from helpers.rasters import write_raster

from aerialmtl.inference.engine_choice import CPU_KINDS, Job, KindEntry, auto_engine, shipped_table
from aerialmtl.inference.engines import ENGINES, EngineSpec
from aerialmtl.inference.engines.names import ENGINE_MODULES, FALLBACK

CPU = torch.device("cpu")
#: window megapixels of a job: a tiny one, a 2048² orthophoto, an 8192² one
TINY, MPX_2048, MPX_8192 = 0.1, 4.875, 79.7


def _specs() -> list[EngineSpec]:
    return [ENGINES[name] for name in ENGINE_MODULES]  # every engine of the package runs a D3-Net on a CPU


@pytest.mark.parametrize("cpu", CPU_KINDS)
@pytest.mark.parametrize(("work", "passes"), [(TINY, 1), (MPX_2048, 1), (MPX_8192, 1), (TINY, 30), (MPX_2048, 30)])
def test_auto_weighs_compiling_on_every_cpu_kind(cpu: str, work: float, passes: int) -> None:
    """A warm cache or a job not known yet: the table's engine where the kind was measured, else the fastest the
    specs declare (today's choice); a cold cache before a job too small to earn the compilation back: the engine
    that compiles nothing, on measured and unmeasured kinds alike."""
    specs, entry = _specs(), shipped_table().get(cpu)  # type: ignore[call-overload]
    today = entry.engine if entry is not None else max(specs, key=lambda s: s.speedup).name
    compiles = next(s for s in specs if s.compile_mpx > 0).name
    assert auto_engine(Job("cpu"), cpu, specs, entry)[0] == today  # type: ignore[arg-type]
    assert auto_engine(Job("cpu", work, passes, frozenset(ENGINE_MODULES)), cpu, specs, entry)[0] == today  # type: ignore[arg-type]
    engine, reason = auto_engine(Job("cpu", work, passes), cpu, specs, entry)  # type: ignore[arg-type]
    too_small = work * passes < 20  # these jobs: 0.1, 3 and 4.9 window Mpx against 6 or 12 of compiling
    if today == compiles and too_small:
        assert engine == FALLBACK and "cache cold" in reason
    else:
        assert engine == today


def test_ice_lake_2048_at_t1_on_a_cold_cache_runs_torch(kind, tmp_path: Path,  # type: ignore[no-untyped-def]
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The case of the issue: AVX-512 without BF16 (not in the table), a cold cache and a small job: the torch
    engine, said so in prediction.json, and a predictor that builds one runner; a warm cache: OpenVINO."""
    pytest.importorskip("openvino")
    from aerialmtl.inference import runner as runner_mod
    from aerialmtl.inference.predict import predict_raster

    kind("avx512")
    assert shipped_table().get("avx512") is None
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(tmp_path / "cache"))
    built: list[str] = []
    init = runner_mod.ModelRunner.__init__

    def counting_init(self, model, meta, settings, resolved, weights_key=None):  # type: ignore[no-untyped-def]
        built.append(resolved.engine)
        init(self, model, meta, settings, resolved, weights_key)

    monkeypatch.setattr(runner_mod.ModelRunner, "__init__", counting_init)
    ortho = write_raster(tmp_path / "o.tif", np.random.default_rng(0).integers(1, 255, (3, 64, 64)).astype(np.uint8))
    predict_raster(ortho, tiny_d3net(), tmp_path / "out", mc=1, progress=False)
    info = json.loads((tmp_path / "out" / "prediction.json").read_text())
    assert (info["engine"], info["engine_choice"]["cpu_kind"]) == (FALLBACK, "avx512")
    assert "cache cold" in info["engine_choice"]["reason"]
    assert built == [FALLBACK]  # one runner, on the engine chosen
    compiling = next(s.name for s in _specs() if s.compile_mpx > 0)
    predict_raster(ortho, tiny_d3net(), tmp_path / "filled", mc=1, progress=False, engine=compiling)
    predict_raster(ortho, tiny_d3net(), tmp_path / "warm", mc=1, progress=False)  # the cache is warm now
    assert json.loads((tmp_path / "warm" / "prediction.json").read_text())["engine"] == compiling
    assert built == [FALLBACK, compiling, compiling]


@pytest.fixture
def fastest_fake(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tests' third engine, registered (last), declaring itself 100× the torch engine and compiling nothing."""
    monkeypatch.setitem(ENGINE_MODULES, fake_engine.NAME, fake_engine.__name__)
    monkeypatch.setattr(fake_engine, "SPEC", dataclasses.replace(fake_engine.SPEC, speedup=100.0))


@pytest.mark.parametrize("cpu", ["avx512_bf16", "avx512"])  # a kind of the table, and one without a measurement
def test_a_third_engine_declared_fastest_is_chosen_by_auto(fastest_fake: None, kind, cpu: str,  # type: ignore[no-untyped-def]
                                                           tmp_path: Path) -> None:
    from aerialmtl.inference.predict import predict_raster

    kind(cpu)
    before = len(fake_engine.BUILT)
    ortho = write_raster(tmp_path / "o.tif", np.random.default_rng(1).integers(1, 255, (3, 48, 48)).astype(np.uint8))
    res = predict_raster(ortho, tiny_d3net(), tmp_path / "out", mc=1, window=32, overlap=8, progress=False)
    info = json.loads((tmp_path / "out" / "prediction.json").read_text())
    assert info["engine"] == fake_engine.NAME and res.windows_computed > 0
    assert len(fake_engine.BUILT) == before + 1 and fake_engine.BUILT[-1].windows == res.windows_computed
    assert "declare" in info["engine_choice"]["reason"]


def test_a_third_engine_that_declares_nothing_is_not_chosen(kind) -> None:  # type: ignore[no-untyped-def]
    """An engine whose spec claims no speed (1.0, the torch engine's) only breaks ties, after those before it."""
    kind("avx512_bf16")
    plain = EngineSpec("plain", "plain", build=lambda setup: None, unusable=lambda device, model: None)  # type: ignore[arg-type,return-value]
    entry = KindEntry(FALLBACK, "fp32", "channels_last", None, "test")
    assert auto_engine(Job("cpu"), "avx512_bf16", [ENGINES[FALLBACK], plain], entry)[0] == FALLBACK
    assert auto_engine(Job("cpu"), "avx512", [ENGINES[FALLBACK], plain], None)[0] == FALLBACK
    fast = dataclasses.replace(plain, speedup=3.0, compile_mpx=6.0)
    assert auto_engine(Job("cpu"), "avx512", [ENGINES[FALLBACK], fast], None)[0] == "plain"
    assert auto_engine(Job("cpu", MPX_2048), "avx512", [ENGINES[FALLBACK], fast], None)[0] == FALLBACK  # cold
    assert auto_engine(Job("cuda"), None, [ENGINES[FALLBACK], fast], None)[0] == FALLBACK  # off the CPU: the order
