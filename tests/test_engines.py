"""The prediction engines: OpenVINO gives the torch engine's maps (fp32 to float rounding, bf16 close on a trained
model), MC dropout included; ``auto`` picks as documented; a missing OpenVINO is a one-line error."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_raster
from helpers.tilefolder import toy_patch

from aerialmtl import runtime
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.inference.engine_choice import choose_engine
from aerialmtl.inference.engines import OPENVINO_INSTALL, resolve_engine, usable_engines
from aerialmtl.inference.predict import Predictor, predict_raster

pytest.importorskip("openvino")


def _layers(folder: Path) -> dict[str, np.ndarray]:
    info = json.loads((folder / "prediction.json").read_text())
    out = {}
    for name, file in info["files"].items():
        if not str(file).endswith(".tif"):  # styles, previews, STAC items
            continue
        with rasterio.open(folder / file) as src:
            out[name] = src.read()
    return out


def _aoi(tmp_path: Path) -> Path:
    ring = [[500004.0, 4999998.0], [500060.0, 4999998.0], [500016.0, 4999960.0], [500004.0, 4999998.0]]
    path = tmp_path / "aoi.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
                    "geometry": {"type": "Polygon", "coordinates": [ring]}}],
                    "crs": {"type": "name", "properties": {"name": "EPSG:32631"}}}))
    return path


@pytest.mark.parametrize("mc", [1, 3])
def test_openvino_fp32_equals_torch(tmp_path: Path, rng: np.random.Generator, mc: int) -> None:
    """Edge windows of other shapes (two rasters, plans of different window sizes), nodata and an AOI."""
    model, meta = tiny_d3net()
    for k, (shape, use_aoi) in enumerate((((100, 70), False), ((90, 130), True))):
        img = rng.integers(1, 256, size=(3, *shape)).astype(np.uint8)
        img[:, shape[0] // 2:, : shape[1] // 3] = 0  # a nodata corner
        ortho = write_raster(tmp_path / f"o{k}.tif", img, nodata=0)
        aoi = _aoi(tmp_path) if use_aoi else None
        maps = {}
        for engine in ("torch", "openvino"):
            out = tmp_path / f"{engine}{k}"
            predict_raster(ortho, (model, meta), out, mc=mc, window=64, overlap=16, batch_size=2, aoi=aoi,
                           precision="fp32", engine=engine, progress=False, seed=5, probabilities=True)
            maps[engine] = _layers(out)
            assert json.loads((out / "prediction.json").read_text())["engine"] == engine
        a, b = maps["torch"], maps["openvino"]
        assert set(a) == set(b)
        np.testing.assert_allclose(b["height"], a["height"], rtol=0, atol=1e-4)
        for name in set(a) - {"height", "classes"}:
            np.testing.assert_allclose(b[name], a[name], rtol=0, atol=1e-4, err_msg=name)
        np.testing.assert_array_equal(b["classes"], a["classes"])
        assert (a["classes"] == 255).any() and (a["classes"] != 255).any()


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny D3-Net trained a little on the toy scene (heights 0/4/8 m, buildings and trees), its
    checkpoint, and a toy orthophoto it has not seen."""
    model, meta = tiny_d3net(k=3)
    root = tmp_path_factory.mktemp("engines")
    rng = np.random.default_rng(0)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    mean = torch.tensor(meta.mean)[:, None, None]
    std = torch.tensor(meta.std)[:, None, None]
    model.train()
    for _ in range(150):
        batch = [toy_patch(rng, 64) for _ in range(4)]
        x = (torch.from_numpy(np.stack([b[0] for b in batch])).float() - mean) / std
        h = torch.from_numpy(np.stack([b[1] for b in batch]))
        c = torch.from_numpy(np.stack([b[2] for b in batch])).long()
        out = model(x)
        loss = (out["height"][:, 0] - h).abs().mean() + torch.nn.functional.cross_entropy(out["classes"], c)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    ckpt = root / "model.pt"
    save_checkpoint(ckpt, model, meta)
    image = np.concatenate([np.concatenate([toy_patch(rng, 64)[0] for _ in range(3)], axis=2) for _ in range(2)],
                           axis=1)
    return ckpt, write_raster(root / "scene.tif", image)


@pytest.mark.parametrize("mc", [1, 4])
def test_openvino_bf16_close_to_torch_fp32_on_a_trained_model(trained: tuple[Path, Path], tmp_path: Path,
                                                               mc: int) -> None:
    ckpt, ortho = trained
    maps = {}
    for engine, precision in (("torch", "fp32"), ("openvino", "bf16")):
        out = tmp_path / engine
        predict_raster(ortho, ckpt, out, mc=mc, window=64, overlap=16, precision=precision, engine=engine,
                       progress=False)
        maps[engine] = _layers(out)
        info = json.loads((out / "prediction.json").read_text())
        assert (info["engine"], info["precision"]) == (engine, precision)
    a, b = maps["torch"], maps["openvino"]
    assert np.abs(a["height"] - b["height"]).mean() <= 0.05
    assert (a["classes"] == b["classes"]).mean() >= 0.995
    assert a["height"].max() > 2.0  # it did learn something


def test_auto_picks_openvino_on_cpu_for_d3net_else_torch(monkeypatch: pytest.MonkeyPatch) -> None:
    from helpers.models import IdentityModel

    model, meta = tiny_d3net()
    cpu = torch.device("cpu")
    assert choose_engine("auto", "auto", cpu, model).engine == "openvino"
    assert [spec.name for spec in usable_engines(torch.device("cuda"), model)] == ["torch"]
    assert choose_engine("auto", "auto", cpu, IdentityModel((1.0,), (1.0,))).engine == "torch"  # not convertible
    pred = Predictor((model, meta), mc=1, window=64, overlap=16, precision="auto")
    assert pred.engine == "openvino"
    assert pred.precision == ("bf16" if runtime.native_bf16(cpu) else "fp32")
    assert Predictor((model, meta), mc=1, engine="torch").precision == ("bf16" if runtime.cpu_has_amx() else "fp32")
    monkeypatch.setitem(sys.modules, "openvino", None)  # import openvino now fails
    assert choose_engine("auto", "auto", cpu, model).engine == "torch"


def test_engines_are_listed_once_and_built_by_name() -> None:
    """The CLI offers the engines of ENGINES; build_engine builds each one, with the Engine protocol's members."""
    import click

    from aerialmtl import runtime
    from aerialmtl.cli.predict import predict
    from aerialmtl.inference.engines import ENGINES, EngineSetup, build_engine
    from aerialmtl.inference.settings import PredictSettings, ResolvedSettings

    choice = next(p.type for p in predict.params if p.name == "engine")
    assert isinstance(choice, click.Choice) and tuple(choice.choices) == ("auto", *ENGINES)
    model, meta = tiny_d3net()
    for name in ENGINES:
        resolved = ResolvedSettings(torch.device("cpu"), name, "fp32", runtime.resolve_threads(), 1)
        engine = build_engine(EngineSetup(model, meta, PredictSettings(), resolved))
        assert engine.name == name and isinstance(engine.model, torch.nn.Module)
        assert isinstance(engine.net, torch.nn.Module) and engine.ahead(4) == 0
        x = torch.zeros(1, 3, 64, 64).contiguous(memory_format=torch.channels_last)
        stats = engine.submit(x, [0], 1, 0, 1).result()
        assert stats.height_mean is not None and tuple(stats.height_mean.shape) == (1, 64, 64)


def test_missing_openvino_is_a_one_line_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                              rng: np.random.Generator, capsys: pytest.CaptureFixture) -> None:
    model, meta = tiny_d3net()
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    ortho = write_raster(tmp_path / "o.tif", rng.integers(1, 256, size=(3, 40, 40)).astype(np.uint8))
    monkeypatch.setitem(sys.modules, "openvino", None)
    with pytest.raises(InputError, match="engine=openvino.*not installed"):
        resolve_engine("openvino", torch.device("cpu"), model)
    code, out, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", "--engine",
                             "openvino", "--quiet")
    message = err.strip()
    assert code != 0 and OPENVINO_INSTALL in message and "--engine" in message
    assert len(message.splitlines()) == 1, message
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("mc", [1, 3])
def test_streams_give_the_maps_of_one_stream(tmp_path: Path, rng: np.random.Generator, mc: int,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Windows (T = 1) and MC samples (T = 3) run in parallel streams, kept in flight while earlier ones are
    stitched: the maps are those of one stream and of the torch engine (fp32; 1e-4 m / 1e-4 nats as the
    fp32 equality above: streams of other widths may sum in another order)."""
    monkeypatch.setattr(runtime, "usable_cpus", lambda: 4)  # three streams even on a 2-core machine
    model, meta = tiny_d3net()
    img = rng.integers(1, 256, size=(3, 150, 110)).astype(np.uint8)
    img[:, 100:, :40] = 0  # an empty window among computed ones
    ortho = write_raster(tmp_path / "o.tif", img, nodata=0)
    maps, infos = {}, {}
    threads = torch.get_num_threads()
    try:
        for label, engine, n in (("torch", "torch", None), ("one", "openvino", 1), ("three", "openvino", 3)):
            out = tmp_path / label
            predict_raster(ortho, (model, meta), out, mc=mc, window=64, overlap=16, batch_size=1, precision="fp32",
                           engine=engine, progress=False, seed=3, threads=n)
            maps[label], infos[label] = _layers(out), json.loads((out / "prediction.json").read_text())
    finally:
        torch.set_num_threads(threads)
    assert infos["one"]["threads"] == {"threads": 1, "streams": 1, "source": "option"}
    assert infos["three"]["threads"] == {"threads": 3, "streams": 3, "source": "option"}
    for label in ("one", "three"):
        for name in maps["torch"]:
            if name == "classes":
                np.testing.assert_array_equal(maps[label][name], maps["torch"][name])
            else:
                np.testing.assert_allclose(maps[label][name], maps["torch"][name], rtol=0, atol=1e-4,
                                           err_msg=f"{label} {name}")


def test_threads_option_env_and_errors(tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """``--threads N`` and ``AERIALMTL_THREADS`` reach the engine and prediction.json; the option wins over
    the variable; bad values are errors naming the option (a usage error) or the variable."""
    model, meta = tiny_d3net()
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    ortho = write_raster(tmp_path / "o.tif", rng.integers(1, 256, size=(3, 40, 40)).astype(np.uint8))
    threads = torch.get_num_threads()
    try:
        monkeypatch.setenv(runtime.THREADS_ENV, "1")
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "env", "--quiet",
                               "--mc", "1")
        assert code == 0, err
        info = json.loads((tmp_path / "env" / "prediction.json").read_text())
        assert info["threads"] == {"threads": 1, "streams": 1, "source": "env"}
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "opt", "--quiet",
                               "--mc", "1", "--threads", "2")
        assert code == 0, err
        info = json.loads((tmp_path / "opt" / "prediction.json").read_text())
        assert info["threads"] == {"threads": 2, "streams": 2, "source": "option"}
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "bad", "--quiet",
                               "--threads", "0")
        assert code == 2 and "Invalid value for --threads" in err and "got '0'" in err, err  # click's usage error
        monkeypatch.setenv(runtime.THREADS_ENV, "many")
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "bad2", "--quiet")
        assert code != 0 and runtime.THREADS_ENV in err and "'many'" in err, err
        monkeypatch.delenv(runtime.THREADS_ENV)
        auto = runtime.resolve_threads("auto")
        assert auto.source == "auto" and auto.threads == torch.get_num_threads()
        assert auto.streams == min(auto.threads, runtime.MAX_STREAMS)
    finally:
        torch.set_num_threads(threads)


def _import_in_fresh_process(code: str, home: Path) -> list[str]:
    """Run ``code`` in a new interpreter with ``HOME=home`` outside any CI (OpenVINO's telemetry stays off in CI);
    its last stdout line, JSON-decoded.
    """
    import os
    import subprocess

    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TF_BUILD", "JENKINS_URL")}
    env["HOME"] = str(home)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return list(json.loads(out.stdout.strip().splitlines()[-1]))


@pytest.mark.skipif(sys.platform != "linux", reason="OpenVINO's telemetry forks on Linux; the home layout is Linux's")
def test_openvino_is_imported_without_its_telemetry(tmp_path):
    """A user's run makes no network call and writes nothing in their home: aerialmtl's import of OpenVINO leaves
    its usage telemetry out (no sender thread, no ``~/intel`` folder), where a plain ``import openvino`` in the
    same environment starts it (the check that this test can fail).
    """
    pytest.importorskip("openvino_telemetry")
    report = ("import json, sys, threading; "
              "print(json.dumps(['openvino_telemetry' in sys.modules] + [t.name for t in threading.enumerate()]))")
    plain, ours = tmp_path / "plain", tmp_path / "ours"
    plain.mkdir()
    ours.mkdir()
    seen = _import_in_fresh_process(f"import openvino; {report}", plain)
    if not (plain / "intel").exists():
        pytest.skip("OpenVINO's telemetry is off in this environment (an opt-out or consent file elsewhere)")
    assert seen[0] is True and len(seen) > 2
    seen = _import_in_fresh_process(
        f"from aerialmtl.runtime import import_openvino; ov = import_openvino(); ov.Core(); {report}", ours)
    assert seen == [False, "MainThread"]
    assert list(ours.iterdir()) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the thread's alternate signal stack (Linux)")
def test_engines_share_one_openvino_core_and_leave_the_signal_stack_in_place(rng: np.random.Generator) -> None:
    """Each OpenVINO Core loads its own CPU plugin, which points the thread's alternate signal stack at a buffer
    of its own and frees it when it goes: engines of their own Cores, dropped in another order than they were
    made, left that stack on freed memory, and a later SIGCHLD (a DataLoader worker's, a subprocess's) corrupted
    data or killed the process (SIGSEGV) at random. Engines made and dropped in any order now leave it as the
    first one set it."""
    import ctypes
    import gc

    class StackT(ctypes.Structure):
        _fields_ = [("ss_sp", ctypes.c_void_p), ("ss_flags", ctypes.c_int), ("ss_size", ctypes.c_size_t)]

    libc = ctypes.CDLL(None, use_errno=True)

    def alt_stack() -> tuple[int | None, int, int]:
        ss = StackT()
        assert libc.sigaltstack(None, ctypes.byref(ss)) == 0
        return ss.ss_sp, ss.ss_flags, ss.ss_size

    model, meta = tiny_d3net()
    x = torch.from_numpy(rng.standard_normal((1, 3, 64, 64)).astype(np.float32))

    def engine_that_ran() -> Predictor:
        pred = Predictor((model, meta), mc=1, window=64, overlap=16, precision="fp32", engine="openvino")
        pred.runner(x, [0])  # compiles: the CPU plugin is loaded by now
        return pred

    first = engine_that_ran()
    where = alt_stack()
    second = engine_that_ran()
    assert first.runner.engine.core is second.runner.engine.core  # type: ignore[attr-defined]
    assert alt_stack() == where
    del first
    gc.collect()
    assert alt_stack() == where  # the older engine gone first: the stack stays where the live plugin put it
    del second
    gc.collect()
    assert alt_stack() == where
