"""``--engine auto`` follows the measured table of its CPU kind (aerialmtl.inference.engine_choice), records why in
prediction.json, says once when an explicit OpenVINO was measured slower; ``aerialmtl bench`` measures the cases
and writes the table the package reads."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import torch
from helpers.models import tiny_d3net

from aerialmtl import runtime
from aerialmtl.errors import ConfigError
from aerialmtl.inference import engine_choice
from aerialmtl.inference.engine_choice import KindEntry, choose_engine, cpu_kind, kind_of, read_table

CPU = torch.device("cpu")


@pytest.mark.parametrize(("flags", "expect"), [
    ({"avx2", "avx512f", "avx512_bf16", "amx_bf16"}, "amx"),
    ({"avx2", "avx512f", "avx512_bf16"}, "avx512_bf16"),
    ({"avx2", "avx512f", "avx512_vnni"}, "avx512"),
    ({"avx2", "fma"}, "avx2"),
    ({"sse4_2"}, "none"),
])
def test_kind_of_flags(flags: set[str], expect: str) -> None:
    assert kind_of(flags) == expect


def test_kind_env_and_isa_cap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(engine_choice.CPU_KIND_ENV, raising=False)
    monkeypatch.delenv(runtime.CPU_FLAGS_ENV, raising=False)
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)  # the suite may run under a cap (.ci/as-cpu)
    monkeypatch.setattr(engine_choice, "_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    try:
        engine_choice.cpu_kind.cache_clear()
        assert cpu_kind() == "avx512_bf16"
        monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")  # the emulation of an AVX2-only CPU
        engine_choice.cpu_kind.cache_clear()
        assert cpu_kind() == "avx2"
        monkeypatch.setenv(engine_choice.CPU_KIND_ENV, "pentium")
        engine_choice.cpu_kind.cache_clear()
        with pytest.raises(ConfigError, match="AERIALMTL_CPU_KIND"):
            cpu_kind()
    finally:
        engine_choice.cpu_kind.cache_clear()


def test_shipped_table_is_valid() -> None:
    table = read_table()
    assert set(table) <= set(engine_choice.CPU_KINDS)
    for entry in table.values():
        assert entry.measured, "every entry says where it was measured"


def test_bad_table_names_the_fix(tmp_path: Path) -> None:
    bad = tmp_path / "t.yaml"
    bad.write_text("kinds:\n  avx2: {engine: onnx, precision: fp32, layout: channels_last}\n")
    with pytest.raises(ConfigError, match="write-table|engine torch"):
        read_table(bad)
    bad.write_text("kinds:\n  z80: {engine: torch, precision: fp32, layout: channels_last}\n")
    with pytest.raises(ConfigError, match="unknown CPU kinds"):
        read_table(bad)


TABLE = {"avx2": KindEntry("torch", "fp32", "channels_last", 1.3, "test", {"torch/fp32": 0.1, "openvino/fp32": 0.07}),
         "avx512_bf16": KindEntry("openvino", "bf16", "openvino", 2.4, "test")}


def test_auto_follows_the_table(kind) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("openvino")
    model = tiny_d3net()[0]
    kind("avx2")
    choice = choose_engine("auto", "auto", CPU, model, TABLE)
    assert (choice.engine, choice.precision, choice.cpu_kind) == ("torch", "fp32", "avx2")
    assert "measured fastest" in choice.reason
    kind("avx512_bf16")
    choice = choose_engine("auto", "auto", CPU, model, TABLE)
    assert (choice.engine, choice.precision) == ("openvino", "bf16")
    assert choose_engine("auto", "fp32", CPU, model, TABLE).precision == "fp32"  # an explicit precision stays
    kind("avx512")  # no measurement: the rule before the table, said so
    choice = choose_engine("auto", "auto", CPU, model, TABLE)
    assert (choice.engine, choice.precision) == ("openvino", "fp32")
    assert "no measurement" in choice.reason


def test_openvino_where_measured_slower_warns_once(kind) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("openvino")
    kind("avx2")
    engine_choice._warned.clear()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        first = choose_engine("openvino", "auto", CPU, tiny_d3net()[0], TABLE)
        choose_engine("openvino", "auto", CPU, tiny_d3net()[0], TABLE)
    assert first.engine == "openvino" and "slower" in first.reason
    assert len([w for w in seen if "slower than the torch engine" in str(w.message)]) == 1
    assert choose_engine("torch", "auto", CPU, tiny_d3net()[0], TABLE).reason == "asked for"


def test_prediction_json_records_the_choice(kind, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    from helpers.rasters import write_raster

    from aerialmtl.inference.predict import predict_raster

    pytest.importorskip("openvino")
    kind("avx2")
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(tmp_path / "cache"))  # cold: nothing compiled yet
    ortho = write_raster(tmp_path / "o.tif", torch.randint(0, 255, (3, 64, 64)).numpy().astype("uint8"))
    expect = engine_choice.shipped_table().get("avx2")

    def run(**options: str) -> dict:  # type: ignore[type-arg]
        predict_raster(ortho, tiny_d3net(), tmp_path / "out", mc=1, progress=False, overwrite=True,
                       **options)  # type: ignore[arg-type]
        return json.loads((tmp_path / "out" / "prediction.json").read_text())  # type: ignore[no-any-return]

    info = run()
    assert info["engine_choice"]["cpu_kind"] == "avx2"
    assert info["engine_choice"]["reason"]
    if expect is None or expect.engine != "openvino" or not expect.speedup:
        return
    # a tiny job on a cold cache: compiling OpenVINO first would take longer than the torch engine, said so
    assert (info["engine"], info["engine_choice"]["engine"]) == ("torch", "torch")
    assert "cache cold" in info["engine_choice"]["reason"]
    run(engine="openvino", precision=expect.precision)  # compiles this model and window into the cache
    info = run()  # the cache is warm now: the table's choice
    assert (info["engine"], info["precision"]) == (expect.engine, expect.precision)


def test_bench_measures_and_writes_the_table(tmp_path: Path) -> None:
    pytest.importorskip("openvino")
    from aerialmtl.inference.cpu_bench import BenchSettings, best_entry, run_bench, write_table

    report = run_bench(BenchSettings(models=("small",), cases=(("torch", "fp32"), ("openvino", "fp32")), window=64,
                                     windows=1, size=0, workdir=tmp_path / "w"))
    rows = {(r.engine, r.precision): r for r in report.rows}
    assert all(r.mpx_s and r.mpx_s > 0 for r in rows.values())
    assert rows["openvino", "fp32"].height_mae_m is not None and rows["openvino", "fp32"].height_mae_m < 1e-3
    assert rows["openvino", "fp32"].class_agreement == pytest.approx(1.0, abs=1e-3)
    assert report.cpu["kind"] in engine_choice.CPU_KINDS
    entry = best_entry(report, model="small")
    assert (entry.engine, entry.precision) in rows
    table = tmp_path / "table.yaml"
    write_table(table, "avx2", entry)
    write_table(table, "amx", KindEntry("openvino", "bf16", "openvino", measured="elsewhere"))
    back = read_table(table)
    assert back["avx2"].engine == entry.engine and back["amx"].measured == "elsewhere"
