"""Provenance covers what GDAL reads beside the file (issue 40, item 2): a world file that moves the raster, an
``.aux.xml`` that declares nodata, an edited sidecar whose date was put back: ``--skip-existing`` recomputes and
says why. Each layer's bytes carry a SHA-256 recorded at commit: a block zeroed in place (same size) is seen.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.errors
from helpers.cli import run_cli
from helpers.models import tiny_d3net

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.formats.prediction import PredictionFolder
from aerialmtl.io.fingerprint import input_fingerprint, sidecar_paths

ARGS = ("--mc", "1", "--window", "64", "--overlap", "16", "--engine", "torch")
WORLD = "0.5\n0.0\n0.0\n-0.5\n500000.25\n5000000.25\n"  # origin at the pixel centre (world-file convention)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("model") / "m.pt"
    save_checkpoint(path, *tiny_d3net())
    return path


def _world_tiff(folder: Path) -> Path:
    """A GeoTIFF with a CRS but no geotransform inside: its place comes from ``o.tfw`` beside it."""
    path = folder / "o.tif"
    data = np.random.default_rng(40).integers(1, 256, size=(3, 48, 64)).astype(np.uint8)
    with warnings.catch_warnings():  # no geotransform inside, on purpose
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "w", driver="GTiff", width=64, height=48, count=3, dtype="uint8",
                           crs="EPSG:32631") as dst:
            dst.write(data)
    path.with_suffix(".tfw").write_text(WORLD)
    return path


def _run(capsys: pytest.CaptureFixture, ortho: Path, ckpt: Path, out: Path) -> str:
    code, stdout, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", out, *ARGS, "--skip-existing")
    assert code == 0, err
    return stdout.strip().splitlines()[-1]


def _origin(out: Path) -> tuple[float, float]:
    with rasterio.open(out / "height.tif") as src:
        return src.transform.c, src.transform.f


def test_a_moved_world_file_is_not_called_complete(tmp_path: Path, ckpt: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    ortho, out = _world_tiff(tmp_path), tmp_path / "pred"
    _run(capsys, ortho, ckpt, out)
    x0, y0 = _origin(out)
    assert x0 == 500000.0  # the world file's place (its origin is a pixel's centre)
    assert _run(capsys, ortho, ckpt, out).endswith("(same model, settings, input)")
    ortho.with_suffix(".tfw").write_text(WORLD.replace("500000.25", "600000.25"))  # 100 km east
    line = _run(capsys, ortho, ckpt, out)
    assert "recomputed" in line and "sidecar o.tfw changed" in line and "raster transform" in line, line
    assert _origin(out) == (x0 + 100000.0, y0)  # the maps are at the new place


def test_an_edited_sidecar_with_its_date_put_back_is_seen(tmp_path: Path, ckpt: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    ortho, out = _world_tiff(tmp_path), tmp_path / "pred"
    tfw = ortho.with_suffix(".tfw")
    _run(capsys, ortho, ckpt, out)
    x0, y0 = _origin(out)
    st = tfw.stat()
    tfw.write_text(WORLD.replace("500000.25", "500100.25"))  # same length, 100 m east
    os.utime(tfw, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert tfw.stat().st_size == st.st_size and tfw.stat().st_mtime_ns == st.st_mtime_ns
    line = _run(capsys, ortho, ckpt, out)
    assert "recomputed" in line and "sidecar o.tfw changed" in line, line
    assert _origin(out) == (x0 + 100.0, y0)


def test_a_new_aux_xml_declaring_nodata_is_seen(tmp_path: Path, ckpt: Path, capsys: pytest.CaptureFixture) -> None:
    ortho, out = _world_tiff(tmp_path), tmp_path / "pred"
    _run(capsys, ortho, ckpt, out)
    aux = ortho.with_name("o.tif.aux.xml")
    aux.write_text("<PAMDataset>" + "".join(
        f'<PAMRasterBand band="{b}"><NoDataValue>0</NoDataValue></PAMRasterBand>' for b in (1, 2, 3))
        + "</PAMDataset>")
    with rasterio.open(ortho) as src:
        assert src.nodatavals == (0.0, 0.0, 0.0)  # GDAL reads it: the raster means something else now
    line = _run(capsys, ortho, ckpt, out)
    assert "recomputed" in line and "sidecar o.tif.aux.xml appeared" in line and "raster nodata" in line, line


def test_every_sidecar_kind_changes_the_fingerprint(tmp_path: Path) -> None:
    ortho = _world_tiff(tmp_path)
    before = input_fingerprint(ortho)
    names = {p.name for p in sidecar_paths(ortho)}
    assert {"o.tfw", "o.wld", "o.prj", "o.tif.aux.xml", "o.tif.ovr", "o.tif.msk", "o.TFW"} <= names
    for name in ("o.wld", "o.prj", "o.tif.ovr", "o.tif.msk"):
        (tmp_path / name).write_bytes(b"x")
        after = input_fingerprint(ortho)
        assert after["sidecars"] != before["sidecars"] and name in after["sidecars"]
        before = after
    os.mkfifo(tmp_path / "o.aux")  # never opened: a FIFO would block the read
    assert input_fingerprint(ortho)["sidecars"]["o.aux"] == {"kind": "p"}


def test_a_zeroed_block_in_a_layer_is_not_called_complete(tmp_path: Path, ckpt: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    ortho, out = _world_tiff(tmp_path), tmp_path / "pred"
    _run(capsys, ortho, ckpt, out)
    info = json.loads((out / "prediction.json").read_text())
    assert set(info["file_sha256"]) == set(info["file_sizes"]) == {"height.tif", "classes.tif"}
    layer = out / "height.tif"
    size = layer.stat().st_size
    with open(layer, "r+b") as f:  # what a disk error leaves: a block of zeros, the size unchanged
        f.seek(size // 2 - 2048)
        f.write(bytes(4096))
    assert layer.stat().st_size == size
    assert PredictionFolder(out).check() == ("height.tif was damaged or changed after the run wrote it (its content "
                                             "does not match the checksum in prediction.json)")
    line = _run(capsys, ortho, ckpt, out)
    assert "recomputed" in line and "height.tif was damaged" in line, line
    assert PredictionFolder(out).check() is None


def test_a_world_file_is_read_after_a_remote_input_in_the_same_process(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The no-listing open of remote inputs must not hide a later local file's world file (predict_many takes
    remote and local inputs in one process): GDAL's options for remote inputs stay out of its open of local files.
    """
    import os

    from aerialmtl.io.align import open_raster
    from aerialmtl.io.paths import REMOTE_OPEN_OPTIONS, configure_remote

    for key in REMOTE_OPEN_OPTIONS:
        monkeypatch.delenv(key, raising=False)
    configure_remote()  # what opening an https:// input does
    assert not set(REMOTE_OPEN_OPTIONS) & set(os.environ)
    with open_raster(_world_tiff(tmp_path), "orthophoto") as src:
        assert src.transform.c == pytest.approx(500000.0)  # the world file's centre origin, half a pixel west
