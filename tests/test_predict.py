"""`predict_raster` / `aerialmtl predict`: georeferencing, nodata, AOI, MC outputs, COG layout, atomicity."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from affine import Affine
from click.testing import CliRunner
from helpers.data import NEON_DIR
from helpers.models import IdentityModel, identity_meta, tiny_d3net
from helpers.rasters import write_raster
from helpers.reference_predict import reference_predict

from aerialmtl.cli import cli
from aerialmtl.cli.options import flags_for
from aerialmtl.errors import OutputExistsError
from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.inference.predict import predict_raster
from aerialmtl.io.cog import cog_problems

UNCERTAINTY = ("height_std.tif", "class_entropy.tif", "class_mutual_info.tif")


@pytest.fixture
def ortho(tmp_path: Path, rng: np.random.Generator) -> Path:
    img = rng.integers(1, 256, size=(3, 90, 130)).astype(np.uint8)
    img[:, 60:, :50] = 0  # nodata corner
    return write_raster(tmp_path / "ortho.tif", img, crs="EPSG:32619", nodata=0,
                        transform=Affine(0.5, 0, 320000.0, 0, -0.5, 4881600.0))


def test_mc_outputs_georeferencing_and_cog_layout(ortho: Path, tmp_path: Path) -> None:
    model, meta = tiny_d3net()
    res = predict_raster(ortho, (model, meta), tmp_path / "pred", mc=4, window=64, overlap=16, probabilities=True,
                         progress=False)
    names = sorted(p.name for p in (tmp_path / "pred").iterdir())
    tifs = ["height.tif", "classes.tif", "class_probabilities.tif", *UNCERTAINTY]
    assert names == sorted([*tifs, *(t.replace(".tif", ".qml") for t in tifs), "item.json", "prediction.json"])
    with rasterio.open(ortho) as src:
        crs, transform, shape = src.crs, src.transform, src.shape
        valid = src.read(1) != 0
    k = meta.model.num_classes
    layers = {}
    for name in ("height", "height_std", "classes", "class_entropy", "class_mutual_info", "class_probabilities"):
        path = res.files[name]
        assert cog_problems(path) == [], name
        with rasterio.open(path) as ds:
            assert ds.crs == crs and ds.transform == transform and ds.shape == shape
            assert ds.block_shapes[0] == (512, 512) and ds.descriptions[0]
            layers[name] = ds.read()
            if name == "classes":
                assert ds.nodata == 255 and ds.colormap(1)[0][:3] == meta.classes.colors[0]  # type: ignore[union-attr]
                assert json.loads(ds.tags()["AERIALMTL_CLASS_SCHEME"]) == meta.classes.to_dict()  # type: ignore[union-attr]
                assert json.loads(ds.tags(1)["class_names"])["0"] == meta.classes.names[0]  # type: ignore[union-attr]
            else:
                assert ds.nodata == -9999.0
            if name in ("height", "height_std"):
                assert ds.units == ("m",) and ds.tags(1)["units"] == "m"
            if name in ("class_entropy", "class_mutual_info"):
                assert ds.units == ("nats",)
    # nodata in every output exactly where the input is nodata
    for name, arr in layers.items():
        nod = 255 if name == "classes" else -9999.0
        assert np.all(arr[:, ~valid] == nod) and np.all(arr[:, valid] != nod), name
    std, ent = layers["height_std"][0][valid], layers["class_entropy"][0][valid]
    mi = layers["class_mutual_info"][0][valid]
    assert std.min() >= 0 and std.max() > 0  # dropout makes samples differ
    assert ent.min() >= 0 and ent.max() <= math.log(k) + 1e-5
    assert np.all(mi >= 0) and np.all(mi <= ent + 1e-6)
    probs = layers["class_probabilities"][:, valid]
    np.testing.assert_allclose(probs.sum(0), 1.0, atol=1e-4)
    np.testing.assert_array_equal(layers["classes"][0][valid], probs.argmax(0))
    info = json.loads((tmp_path / "pred" / "prediction.json").read_text())
    assert info["mc_samples"] == 4 and info["window"] == 64 and info["overlap"] == 16
    assert info["overlap_factor"] == pytest.approx(res.overlap_factor) and "total" in info["timings_s"]


def test_single_pass_writes_no_uncertainty_and_skips_empty_windows(tmp_path: Path, rng: np.random.Generator) -> None:
    img = rng.integers(1, 256, size=(3, 100, 100)).astype(np.uint8)
    img[:, :, :64] = 0  # the whole left window column is nodata
    src = write_raster(tmp_path / "o.tif", img, nodata=0)
    meta = identity_meta()
    res = predict_raster(src, (IdentityModel(meta.mean, meta.std), meta), tmp_path / "p", mc=1, window=64, overlap=0,
                         precision="fp32", progress=False)
    assert res.windows_total == 4 and res.windows_computed == 2
    assert not any((tmp_path / "p" / f).exists() for f in UNCERTAINTY)
    with rasterio.open(res.files["height"]) as ds:
        h = ds.read(1)
    assert np.all(h[:, :64] == -9999.0)
    np.testing.assert_array_equal(h[:, 64:], img[0, :, 64:].astype(np.float32))


def test_aoi_limits_computation_and_output(tmp_path: Path, rng: np.random.Generator) -> None:
    img = rng.integers(1, 256, size=(3, 128, 128)).astype(np.uint8)
    src = write_raster(tmp_path / "o.tif", img, crs="EPSG:32631")  # 0.5 m pixels from (500000, 5000000)
    aoi = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "EPSG:32631"}},
           "features": [{"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [[
               [500000.0, 5000000.0], [500020.0, 5000000.0], [500020.0, 4999980.0], [500000.0, 4999980.0],
               [500000.0, 5000000.0]]]}}]}
    (tmp_path / "aoi.geojson").write_text(json.dumps(aoi))
    meta = identity_meta()
    res = predict_raster(src, (IdentityModel(meta.mean, meta.std), meta), tmp_path / "p", mc=1, window=64, overlap=0,
                         precision="fp32", aoi=tmp_path / "aoi.geojson", progress=False)
    assert res.windows_computed == 1 and res.windows_total == 4
    with rasterio.open(res.files["height"]) as ds:
        h = ds.read(1)
    np.testing.assert_array_equal(h[:40, :40], img[0, :40, :40].astype(np.float32))  # 20 m = 40 px inside
    assert np.all(h[40:, :] == -9999.0) and np.all(h[:, 40:] == -9999.0)


class _FailingModel(IdentityModel):
    calls = 0

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        type(self).calls += 1
        if type(self).calls == 2:
            raise RuntimeError("injected failure")
        return super().forward(x)


def test_failure_mid_run_leaves_no_file_at_a_final_path(ortho: Path, tmp_path: Path) -> None:
    meta = identity_meta()
    out = tmp_path / "p"
    with pytest.raises(RuntimeError, match="injected"):
        predict_raster(ortho, (_FailingModel(meta.mean, meta.std), meta), out, mc=1, window=32, overlap=0,
                       batch_size=1, progress=False)
    assert not out.exists() or list(out.iterdir()) == []


def test_existing_outputs_are_refused_then_overwritten_without_stale_files(ortho: Path, tmp_path: Path) -> None:
    meta = identity_meta()
    model = IdentityModel(meta.mean, meta.std, dropout=0.5)
    out = tmp_path / "p"
    predict_raster(ortho, (model, meta), out, mc=3, window=64, overlap=16, progress=False)
    assert (out / "height_std.tif").exists()
    with pytest.raises(OutputExistsError, match="overwrite=True"):
        predict_raster(ortho, (model, meta), out, mc=1, window=64, overlap=16, progress=False)
    predict_raster(ortho, (model, meta), out, mc=1, window=64, overlap=16, overwrite=True, progress=False)
    assert not any((out / f).exists() for f in UNCERTAINTY)  # stale T>1 maps removed
    assert json.loads((out / "prediction.json").read_text())["mc_samples"] == 1
    assert sorted(p.name for p in out.iterdir()) == ["classes.qml", "classes.tif", "height.qml", "height.tif",
                                                     "item.json", "prediction.json"]


def test_cli_several_inputs_one_folder_each(ortho: Path, tmp_path: Path) -> None:
    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "m.pt", model, meta)
    other = tmp_path / "second.tif"
    other.write_bytes(ortho.read_bytes())
    runner = CliRunner()
    r = runner.invoke(cli, ["predict", str(ortho), str(other), "--model", str(tmp_path / "m.pt"), "--out",
                            str(tmp_path / "out"), "--mc", "2", "--window", "64", "--overlap", "16", "--quiet"])
    assert r.exit_code == 0, r.output
    for stem in ("ortho", "second"):
        info = json.loads((tmp_path / "out" / stem / "prediction.json").read_text())
        assert info["checkpoint"] == str(tmp_path / "m.pt") and (tmp_path / "out" / stem / "class_entropy.tif").exists()
    r = runner.invoke(cli, ["predict", str(ortho), "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "x"),
                            "--window", "100"])
    assert r.exit_code == 2 and "--window" in r.output
    with pytest.warns(FutureWarning, match="--tile is deprecated.*--window"):  # the former name still works
        r = runner.invoke(cli, ["predict", str(ortho), "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "x"),
                                "--tile", "100"])
    assert r.exit_code == 2 and "--window" in r.output


@pytest.mark.skipif(not (NEON_DIR / "rgb_0p1m.tif").is_file(), reason="NEON sample data not available")
def test_neon_ortho_is_resampled_to_the_model_gsd(tmp_path: Path) -> None:
    ortho = NEON_DIR / "rgb_0p1m.tif"
    model, meta = tiny_d3net(gsd=0.5)
    with pytest.warns(UserWarning, match=r"0\.1 m.*0\.5 m"):
        res = predict_raster(ortho, (model, meta), tmp_path / "p", mc=1, window=128, overlap=32, progress=False)
    with rasterio.open(ortho) as src, rasterio.open(res.files["height"]) as out:
        assert out.crs == src.crs
        assert out.res == (0.5, 0.5)
        assert (out.transform.c, out.transform.f) == pytest.approx((src.bounds.left, src.bounds.top))
        assert out.bounds.right >= src.bounds.right - 1e-6 and out.bounds.bottom <= src.bounds.bottom + 1e-6
        assert out.bounds.right - src.bounds.right < 0.5 and src.bounds.bottom - out.bounds.bottom < 0.5
        h = out.read(1, masked=True)
        assert h.count() > 0.95 * h.size  # valid almost everywhere (last partial pixels may be nodata)


class _RecordingModel(IdentityModel):
    """Identity model that records the batch size of every decoder call."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.decoded: list[int] = []

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        self.decoded.append(int(feats[0].shape[0]))
        return super().decode(feats)


def test_mc_samples_are_decoded_in_chunks_that_fit_the_pixel_budget(ortho: Path, tmp_path: Path) -> None:
    meta = identity_meta()
    model = _RecordingModel(meta.mean, meta.std, dropout=0.5)
    budget = 5 * 64 * 64  # at most 5 decoded 64² images per call
    res = predict_raster(ortho, (model, meta), tmp_path / "p", mc=7, window=64, overlap=16, batch_size=2,
                         max_decode_pixels=budget, progress=False)
    assert model.decoded and max(model.decoded) * 64 * 64 <= budget
    assert sum(model.decoded) == 7 * res.windows_computed  # every window got all T samples
    with rasterio.open(res.files["height"]) as h, rasterio.open(ortho) as src:
        valid = src.read(1) != 0
        # height is a deterministic branch of the identity model: MC chunking must not change it
        np.testing.assert_allclose(h.read(1)[valid], src.read(1)[valid].astype(np.float32), atol=1e-3)


def test_precision_auto_follows_native_bf16_and_bad_values_name_the_option(monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl import runtime
    from aerialmtl.errors import InputError
    from aerialmtl.inference.runner import mc_sample_batch
    from aerialmtl.runtime import resolve_precision

    monkeypatch.setattr(runtime, "native_bf16", lambda device: True)
    assert resolve_precision("auto", torch.device("cpu")) == "fp32"  # torch's CPU path: fp32 (bench/RESULTS.md)
    assert resolve_precision("auto", torch.device("cpu"), cpu_bf16=True) == "bf16"  # the OpenVINO engine
    assert resolve_precision("auto", torch.device("cuda")) == "bf16"
    monkeypatch.setattr(runtime, "native_bf16", lambda device: False)
    assert resolve_precision("auto", torch.device("cpu"), cpu_bf16=True) == "fp32"
    assert resolve_precision("auto", torch.device("cuda")) == "fp32"
    assert resolve_precision("bf16", torch.device("cpu")) == "bf16"
    with pytest.raises(InputError, match="precision=fp16 is not supported"):
        resolve_precision("fp16", torch.device("cpu"))
    assert mc_sample_batch(2, 512, 512, torch.device("cpu"), max_pixels=2**21) == 4
    assert mc_sample_batch(8, 1024, 1024, torch.device("cpu"), max_pixels=2**21) == 1  # never 0


# ---- the streaming path against a whole-raster reference ------------------------------------------
def _read_layers(folder: Path) -> dict[str, np.ndarray]:
    out = {}
    for path in folder.glob("*.tif"):
        with rasterio.open(path) as ds:
            out[path.stem] = ds.read()
    return out


EQUIVALENCE = {  # shape, tile, overlap, nodata corner, AOI
    "nodata corner": ((90, 130), 64, 16, True, False),
    "3-way overlaps": ((150, 97), 64, 32, False, False),
    "aoi": ((70, 200), 96, 24, False, True),
    "one window": ((40, 45), 64, 16, True, False),
}


@pytest.mark.parametrize("mc", [1, 3])
@pytest.mark.parametrize("case", list(EQUIVALENCE))
def test_outputs_equal_a_whole_raster_reference(tmp_path: Path, rng: np.random.Generator, case: str, mc: int) -> None:
    """Floats within 1e-5 and classes equal (T = 1: bit for bit) to a whole-raster-in-memory blend."""
    shape, tile, overlap, corner, use_aoi = EQUIVALENCE[case]
    img = rng.integers(1, 256, size=(3, *shape)).astype(np.uint8)
    if corner:
        img[:, shape[0] // 2:, : shape[1] // 3] = 0
    ortho = write_raster(tmp_path / "o.tif", img, nodata=0)
    aoi = None
    if use_aoi:  # a triangle over part of the raster (0.5 m pixels from (500000, 5000000))
        ring = [[500005.0, 4999999.0], [500090.0, 4999999.0], [500020.0, 4999970.0], [500005.0, 4999999.0]]
        aoi = tmp_path / "aoi.geojson"
        aoi.write_text(json.dumps({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
                       "geometry": {"type": "Polygon", "coordinates": [ring]}}],
                       "crs": {"type": "name", "properties": {"name": "EPSG:32631"}}}))
    model, meta = tiny_d3net()
    res = predict_raster(ortho, (model, meta), tmp_path / "p", mc=mc, window=tile, overlap=overlap, batch_size=2,
                         aoi=aoi, probabilities=True, progress=False, seed=3, engine="torch", precision="fp32")
    ref = reference_predict(ortho, model, meta, mc=mc, tile=tile, overlap=overlap, batch_size=2, aoi=aoi, seed=3)
    got = _read_layers(tmp_path / "p")
    assert set(got) == set(ref) == {n for n in res.files if n != "prediction"}
    valid = got["classes"][0] != 255
    assert valid.any() and (~valid).any() == (corner or use_aoi)
    for name, arr in ref.items():
        if name == "classes":
            continue
        if mc == 1:
            np.testing.assert_array_equal(got[name], arr, err_msg=name)
        else:
            np.testing.assert_allclose(got[name], arr, rtol=0, atol=1e-5, err_msg=name)
    if mc == 1:
        np.testing.assert_array_equal(got["classes"], ref["classes"])
    else:  # equal wherever the two best classes are not tied to float precision
        probs = np.sort(ref["class_probabilities"][:, valid], axis=0)
        clear = probs[-1] - probs[-2] > 1e-5
        assert clear.mean() > 0.99
        np.testing.assert_array_equal(got["classes"][0][valid][clear], ref["classes"][0][valid][clear])
        assert (got["classes"][0][~valid] == 255).all()


@pytest.mark.parametrize("engine", ["torch", "openvino"])
def test_results_do_not_depend_on_batch_size_or_sample_chunks(ortho: Path, tmp_path: Path, engine: str) -> None:
    model, meta = tiny_d3net()
    outs = []
    for k, (batch, budget) in enumerate(((1, None), (3, 2 * 64 * 64))):
        predict_raster(ortho, (model, meta), tmp_path / f"p{k}", mc=4, window=64, overlap=16, batch_size=batch,
                       max_decode_pixels=budget, progress=False, engine=engine)
        outs.append(_read_layers(tmp_path / f"p{k}"))
    for name in outs[0]:  # the same per-window dropout masks: only float rounding differs
        np.testing.assert_allclose(outs[0][name], outs[1][name], rtol=0, atol=1e-5, err_msg=name)


def test_batch_size_auto_and_compile_fallback(ortho: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.inference.runner import CPU_BATCH, batch_from_memory

    def broken_compile(fn, *a, **k):  # noqa: ANN001, ANN202 - stands in for torch.compile
        def call(*args, **kwargs):  # noqa: ANN202
            raise RuntimeError("no C++ compiler found")
        return call

    monkeypatch.setattr(torch, "compile", broken_compile)
    model, meta = tiny_d3net()
    with pytest.warns(UserWarning, match="torch.compile is not available here .*no C\\+\\+ compiler"):
        res = predict_raster(ortho, (model, meta), tmp_path / "p", mc=1, window=64, overlap=16, batch_size="auto",
                             compile=True, progress=False, engine="torch")
    info = json.loads((tmp_path / "p" / "prediction.json").read_text())
    assert info["batch_size"] == CPU_BATCH and info["compile"] is True and res.windows_computed > 0
    plain = predict_raster(ortho, (model, meta), tmp_path / "q", mc=1, window=64, overlap=16, batch_size=CPU_BATCH,
                           progress=False, engine="torch")
    for name in ("height", "classes"):
        with rasterio.open(res.files[name]) as a, rasterio.open(plain.files[name]) as b:
            np.testing.assert_array_equal(a.read(), b.read())
    assert batch_from_memory(10 * 2**30, 2**30) == 6 and batch_from_memory(2**20, 2**30) == 1


def _three_inputs(tmp_path: Path, rng: np.random.Generator) -> list[Path]:
    """Three overlapping 60 × 70 px RGB orthophotos, ``t0.tif`` … ``t2.tif`` in ``tmp_path``."""
    paths = []
    for k, (x0, y0) in enumerate(((500000.0, 5000000.0), (500030.0, 4999990.0), (500080.0, 5000020.0))):
        img = rng.integers(1, 256, size=(3, 60, 70)).astype(np.uint8)
        paths.append(write_raster(tmp_path / f"t{k}.tif", img, transform=Affine(0.5, 0, x0, 0, -0.5, y0)))
    return paths


def test_several_inputs_mosaic_and_skip_existing(tmp_path: Path, rng: np.random.Generator) -> None:
    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "m.pt", model, meta)
    paths = _three_inputs(tmp_path, rng)
    args = ["predict", *map(str, paths), "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "out"),
            "--mc", "2", "--window", "64", "--overlap", "16", "--quiet"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    out = tmp_path / "out"
    for name in ("height", "classes", "class_entropy"):
        with rasterio.open(out / f"{name}.mosaic.vrt") as vrt:
            left, bottom, right, top = vrt.bounds
            for path in paths:
                with rasterio.open(path) as src, rasterio.open(out / path.stem / f"{name}.tif") as layer:
                    b = src.bounds
                    assert left <= b.left and bottom <= b.bottom and right >= b.right and top >= b.top
                    win = vrt.window(*layer.bounds)  # the mosaic shows each input's own values where it alone lies
                    mos = vrt.read(1, window=win)
                    own = layer.read(1)
                    assert mos.shape == own.shape and (mos == own).mean() > 0.5
            assert vrt.crs == "EPSG:32631" and vrt.res == (0.5, 0.5)
    stamp = (out / "t1" / "height.tif").stat().st_mtime_ns
    (out / "t2" / "prediction.json").unlink()  # as if the run had stopped before t2 was complete
    (out / "t2" / "height.tif").unlink()
    r = CliRunner().invoke(cli, [*args, "--skip-existing", "--overwrite"])
    assert r.exit_code == 0, r.output
    assert "t0.tif: skipped" in r.output and "t1.tif: skipped" in r.output and "t2.tif →" in r.output
    assert (out / "t1" / "height.tif").stat().st_mtime_ns == stamp and (out / "t2" / "height.tif").exists()
    r = CliRunner().invoke(cli, args)  # without --skip-existing or --overwrite: refused before any work
    assert r.exit_code == 1 and "--overwrite" in r.exception.render(flags_for("predict"))


@pytest.mark.parametrize("mc", [1, 3])
def test_stitching_in_a_thread_of_its_own_writes_the_same_maps(ortho: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch, mc: int) -> None:
    """The stitch stage in its own thread (a GPU, or a host of 2 cores or more) and in the model loop (one
    core) give byte-identical layers: the windows reach the stitcher in the same order.
    """
    from aerialmtl.inference import strips as model_mod

    assert model_mod.stitch_in_thread(torch.device("cpu"), 1) is False
    assert model_mod.stitch_in_thread(torch.device("cpu"), 2) is True
    assert model_mod.stitch_in_thread(torch.device("cpu"), 16) is True
    assert model_mod.stitch_in_thread(torch.device("cuda")) is True
    files = {}
    for cores in (1, 10**6):  # threaded, then in the model loop
        monkeypatch.setattr(model_mod, "STITCH_THREAD_CORES", cores)
        res = predict_raster(ortho, tiny_d3net(), tmp_path / f"p{cores}", mc=mc, window=64, overlap=16,
                             batch_size=2, progress=False)
        files[cores] = {n: p.read_bytes() for n, p in res.files.items() if p.suffix == ".tif"}
    assert files[1].keys() == files[10**6].keys() and len(files[1]) >= 2
    for name in files[1]:
        assert files[1][name] == files[10**6][name], name


def test_a_failure_in_the_stitch_thread_fails_the_run_and_ends_the_thread(ortho: Path, tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import threading

    from aerialmtl.inference import strips as model_mod
    from aerialmtl.inference.stitch import Stitcher

    monkeypatch.setattr(model_mod, "STITCH_THREAD_CORES", 1)
    calls = {"n": 0}
    add = Stitcher.add

    def failing_add(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("injected stitch failure")
        return add(self, *args, **kwargs)

    monkeypatch.setattr(Stitcher, "add", failing_add)
    out = tmp_path / "p"
    with pytest.raises(RuntimeError, match="injected stitch failure"):
        predict_raster(ortho, tiny_d3net(), out, mc=1, window=32, overlap=0, batch_size=1, progress=False)
    assert not out.exists() or list(out.iterdir()) == []  # no final file, no hidden file
    assert not [t for t in threading.enumerate() if t.name == "aerialmtl-stitch"]


def _stopped_after_the_first(paths: list[Path], tmp_path: Path, stop: type[BaseException], match: str) -> Path:
    """Predict ``paths`` into ``tmp_path / "out"``, which must stop with ``stop`` once the first input is complete
    and reported (and no other); the output folder."""
    from aerialmtl.inference.jobs import predict_many

    seen: list[str] = []
    with pytest.raises(stop, match=match):
        predict_many(paths, tiny_d3net(), tmp_path / "out", window=64, overlap=16, progress=False,
                     on_result=lambda r: seen.append(r.out_dir.name))
    out = tmp_path / "out"
    assert seen == [paths[0].stem] and (out / paths[0].stem / "prediction.json").is_file()
    return out


def _left(folder: Path) -> list[str]:
    """Every file left in ``folder`` (hidden ones included), or nothing when there is no folder."""
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


@pytest.mark.parametrize("in_thread", [True, False])
def test_each_input_is_committed_beside_the_next_strip_and_reported_in_order(
        tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch, in_thread: bool) -> None:
    """Several inputs: on a GPU an input's COGs are built in the commit thread while the next input computes
    (issue 46), on a CPU in the main thread after its strip; either way the results come in input order, each once
    its folder is complete, and the maps are those of one input at a time."""
    import threading

    from aerialmtl.inference import jobs
    from aerialmtl.inference.job import InputJob
    from aerialmtl.inference.jobs import predict_many

    assert jobs.commits_in_thread(torch.device("cpu")) is False
    assert jobs.commits_in_thread(torch.device("cuda")) is True
    monkeypatch.setattr(jobs, "commits_in_thread", lambda device: in_thread)
    paths = _three_inputs(tmp_path, rng)
    model = tiny_d3net()
    alone = {p.stem: predict_raster(p, model, tmp_path / "alone" / p.stem, mc=2, window=64, overlap=16,
                                    progress=False) for p in paths}
    threads: list[str] = []
    real = InputJob.commit_files

    def commit_files(self: InputJob, *args, **kwargs):  # type: ignore[no-untyped-def]
        threads.append(threading.current_thread().name)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(InputJob, "commit_files", commit_files)
    seen: list[tuple[str, bool]] = []
    predict_many(paths, model, tmp_path / "out", mc=2, window=64, overlap=16, progress=False,
                 on_result=lambda r: seen.append((r.out_dir.name, (r.out_dir / "prediction.json").is_file())))
    assert seen == [("t0", True), ("t1", True), ("t2", True)]
    assert len(threads) == 3
    assert all(n.startswith("aerialmtl-commit") if in_thread else n == "MainThread" for n in threads), threads
    for p in paths:
        for name in ("height", "classes", "class_entropy", "class_mutual_info", "height_std"):
            with rasterio.open(tmp_path / "out" / p.stem / f"{name}.tif") as a, \
                    rasterio.open(alone[p.stem].files[name]) as b:
                np.testing.assert_array_equal(a.read(), b.read())


@pytest.mark.parametrize("in_thread", [True, False])
def test_a_failed_commit_stops_the_run_and_leaves_no_file_of_it_or_of_the_strip_beside_it(
        tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch, in_thread: bool) -> None:
    from aerialmtl.inference import jobs
    from aerialmtl.inference.writer import PredictionWriter

    monkeypatch.setattr(jobs, "commits_in_thread", lambda device: in_thread)

    paths = _three_inputs(tmp_path, rng)
    real = PredictionWriter.convert

    def convert(self: PredictionWriter, *args, **kwargs):  # type: ignore[no-untyped-def]
        if self.out_dir.name == "t1":
            raise OSError(28, "No space left on device (injected)")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(PredictionWriter, "convert", convert)
    out = _stopped_after_the_first(paths, tmp_path, Exception, "No space left on device")
    assert _left(out / "t1") == [] and _left(out / "t2") == []  # no final file, no hidden staging file


@pytest.mark.parametrize("stop", [KeyboardInterrupt, RuntimeError])
def test_a_stop_in_a_strip_lets_the_commit_beside_it_finish(
        tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch, stop: type[BaseException]) -> None:
    """Ctrl-C (or an error) while input 2 computes beside input 1's commit thread: input 1, computed whole, is
    still committed and reported; input 2 leaves nothing; the stop propagates."""
    from aerialmtl.inference import jobs
    from aerialmtl.inference.model import Predictor

    monkeypatch.setattr(jobs, "commits_in_thread", lambda device: True)

    paths = _three_inputs(tmp_path, rng)
    real = Predictor.compute

    def compute(self: Predictor, src, *args, **kwargs):  # type: ignore[no-untyped-def]
        if Path(src.path).stem == "t1":
            raise stop("stopped (injected)")
        return real(self, src, *args, **kwargs)

    monkeypatch.setattr(Predictor, "compute", compute)
    out = _stopped_after_the_first(paths, tmp_path, stop, "injected")
    assert _left(out / "t1") == [] and not (out / "t2").exists()


@pytest.mark.parametrize("in_thread", [True, False])
def test_a_record_that_cannot_be_made_fails_its_input_without_leaving_files(
        tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch, in_thread: bool) -> None:
    """The model's fields of prediction.json are read before the commit starts (in the main thread): a failure
    there is the input's failure like any in the commit, and its staging files go."""
    from aerialmtl.inference import jobs
    from aerialmtl.inference.model import Predictor

    monkeypatch.setattr(jobs, "commits_in_thread", lambda device: in_thread)
    paths = _three_inputs(tmp_path, rng)
    real = Predictor.record_settings

    def record_settings(self: Predictor, src):  # type: ignore[no-untyped-def]
        if Path(src.path).stem == "t1":
            raise ValueError("record (injected)")
        return real(self, src)

    monkeypatch.setattr(Predictor, "record_settings", record_settings)
    out = _stopped_after_the_first(paths, tmp_path, ValueError, "injected")
    assert _left(out / "t1") == []
