"""Inputs anywhere GDAL reads, and `aerialmtl predict ORTHO` with its defaults (--out, AERIALMTL_MODEL)."""

from __future__ import annotations

import functools
import http.server
import os
import re
import shutil
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_prediction_folder, write_raster

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.io.paths import gdal_path, is_local, is_remote, raster_name, raster_stem

ARGS = ("--mc", "2", "--window", "64", "--overlap", "16", "--quiet")


# ---- a static file server that honours Range requests (http.server alone ignores them) --------------
class RangeHandler(http.server.SimpleHTTPRequestHandler):
    """Serves files of its directory; ``Range: bytes=a-b`` answers 206 with those bytes, as COG readers need."""

    def send_head(self):  # type: ignore[no-untyped-def]
        path = Path(self.translate_path(self.path))
        match = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        if not path.is_file() or match is None:
            return super().send_head()
        size = path.stat().st_size
        start = int(match.group(1))
        end = min(int(match.group(2)) if match.group(2) else size - 1, size - 1)
        if start >= size:
            self.send_error(416)
            return None
        f = path.open("rb")
        f.seek(start)
        self.send_response(206)
        self.send_header("Content-Type", "image/tiff")
        self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Content-Length", str(end - start + 1))
        self.send_header("Accept-Ranges", "bytes")
        self.end_headers()
        self.ranges.append((start, end))
        return _Slice(f, end - start + 1)

    ranges: list[tuple[int, int]] = []

    def log_message(self, *args: object) -> None:
        pass


class _Slice:
    """A file object that returns at most ``n`` bytes (what ``copyfile`` sends for a range)."""

    def __init__(self, f, n: int) -> None:  # type: ignore[no-untyped-def]
        self.f, self.left = f, n

    def read(self, size: int = -1) -> bytes:
        size = self.left if size < 0 else min(size, self.left)
        data = self.f.read(size)
        self.left -= len(data)
        return data

    def close(self) -> None:
        self.f.close()


@pytest.fixture
def server(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """``(base URL, served folder)`` of a local HTTP server on 127.0.0.1 with range requests."""
    root = tmp_path / "www"
    root.mkdir()
    RangeHandler.ranges = []
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(RangeHandler, directory=str(root)))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", root
    finally:
        httpd.shutdown()
        httpd.server_close()


def _cog(path: Path, rng: np.random.Generator) -> Path:
    img = rng.integers(1, 256, size=(3, 96, 128)).astype(np.uint8)
    img[:, 70:, :40] = 0
    tmp = write_raster(path.with_suffix(".plain.tif"), img, crs="EPSG:32619", nodata=0,
                       transform=Affine(0.5, 0, 320000.0, 0, -0.5, 4881600.0))
    with rasterio.open(tmp) as src:
        profile = src.profile.copy()
        profile.update(driver="COG", compress="DEFLATE", blocksize=64)
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(src.read())
    tmp.unlink()
    return path


@pytest.fixture
def model_path(tmp_path: Path) -> Path:
    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "m.pt", model, meta)
    return tmp_path / "m.pt"


def _layers(folder: Path) -> dict[str, np.ndarray]:
    out = {}
    for f in sorted(folder.glob("*.tif")):
        with rasterio.open(f) as src:
            out[f.name] = src.read()
    return out


# ---- paths --------------------------------------------------------------------------------------------
def test_urls_become_gdal_paths_and_local_paths_stay() -> None:
    assert gdal_path("https://h.org/a/o.tif") == "/vsicurl/https://h.org/a/o.tif"
    assert gdal_path("s3://bucket/dir/o.tif") == "/vsis3/bucket/dir/o.tif"
    assert gdal_path("gs://b/o.tif") == "/vsigs/b/o.tif"
    assert gdal_path(Path("data/o.tif")) == "data/o.tif"
    assert gdal_path("/vsizip/a.zip/o.tif") == "/vsizip/a.zip/o.tif"
    assert is_remote("s3://b/o.tif") and is_remote("/vsizip//vsicurl/https://h/a.zip/o.tif")
    assert not is_remote("/vsizip/a.zip/o.tif") and not is_local("/vsizip/a.zip/o.tif")
    assert is_local("o.tif") and is_local(Path("/x/o.tif")) and not is_local("https://h/o.tif")
    assert raster_name("https://h/a/o.tif?X-Amz-Signature=1") == "o.tif" and raster_stem("s3://b/d/o.tif") == "o"


# ---- predict: defaults ---------------------------------------------------------------------------------
def test_predict_ortho_with_the_model_from_the_environment_writes_beside_it(
        tmp_path: Path, rng: np.random.Generator, model_path: Path, capsys: pytest.CaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "data").mkdir()
    ortho = _cog(tmp_path / "data" / "ortho.tif", rng)
    monkeypatch.delenv("AERIALMTL_MODEL", raising=False)
    code, out, err = run_cli(capsys, "predict", ortho, *ARGS)
    assert code == 1 and len(err.strip().splitlines()) == 1
    assert "--model" in err and "AERIALMTL_MODEL" in err and "Traceback" not in err
    assert not (tmp_path / "data" / "ortho_aerialmtl").exists()

    monkeypatch.setenv("AERIALMTL_MODEL", str(model_path))
    monkeypatch.chdir(tmp_path)  # the default is beside the input, not in the current folder
    code, out, err = run_cli(capsys, "predict", ortho, *ARGS)
    assert code == 0, err
    folder = tmp_path / "data" / "ortho_aerialmtl"
    assert (folder / "height.tif").is_file() and (folder / "prediction.json").is_file()
    assert f"outputs in {folder}" in out

    # several inputs: one folder for the run (sub-folder per input + mosaics) in their common folder
    shutil.copy(ortho, tmp_path / "data" / "second.tif")
    code, out, err = run_cli(capsys, "predict", ortho, tmp_path / "data" / "second.tif", *ARGS)
    assert code == 0, err
    many = tmp_path / "data" / "aerialmtl_predictions"
    assert (many / "ortho" / "height.tif").is_file() and (many / "second" / "height.tif").is_file()
    assert (many / "height.mosaic.vrt").is_file()


# ---- predict: remote inputs ----------------------------------------------------------------------------
def test_a_cog_served_over_http_predicts_like_the_local_file(
        tmp_path: Path, rng: np.random.Generator, model_path: Path, server: tuple[str, Path],
        capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    url, root = server
    local = _cog(root / "ortho.tif", rng)
    code, _, err = run_cli(capsys, "predict", local, "--model", model_path, "--out", tmp_path / "local", *ARGS)
    assert code == 0, err
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(capsys, "predict", f"{url}/ortho.tif", "--model", model_path, *ARGS)
    assert code == 0, err
    assert RangeHandler.ranges, "GDAL read the COG through range requests"
    remote = tmp_path / "ortho_aerialmtl"  # a remote input's default folder is in the current folder
    a, b = _layers(tmp_path / "local"), _layers(remote)
    assert a.keys() == b.keys() and "height.tif" in a
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    info = (remote / "prediction.json").read_text()
    assert f"/vsicurl/{url}/ortho.tif" in info

    # the same file inside a zip archive, read through /vsizip/ over /vsicurl/
    with zipfile.ZipFile(root / "tiles.zip", "w") as z:
        z.write(local, "ortho.tif")
    code, _, err = run_cli(capsys, "predict", f"/vsizip//vsicurl/{url}/tiles.zip/ortho.tif", "--model", model_path,
                           "--out", tmp_path / "zipped", *ARGS)
    assert code == 0, err
    c = _layers(tmp_path / "zipped")
    for name in a:
        np.testing.assert_array_equal(a[name], c[name], err_msg=name)


def test_a_bad_url_ends_in_one_line_and_leaves_nothing(
        tmp_path: Path, model_path: Path, server: tuple[str, Path], capsys: pytest.CaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    url, _ = server
    monkeypatch.chdir(tmp_path)
    before = sorted(os.listdir(tmp_path))
    for bad in (f"{url}/missing.tif", "http://127.0.0.1:9/refused.tif"):
        code, out, err = run_cli(capsys, "predict", bad, "--model", model_path, *ARGS)
        lines = [line for line in err.splitlines() if line.startswith("Error")]
        assert code == 1 and len(lines) == 1 and "Traceback" not in err, err
        assert "cannot be opened" in lines[0] and "check the URL" in lines[0]
        assert sorted(os.listdir(tmp_path)) == before  # no partial output, not even an empty folder


def test_tile_and_evaluate_read_remote_rasters(
        tmp_path: Path, rng: np.random.Generator, server: tuple[str, Path], capsys: pytest.CaptureFixture) -> None:
    url, root = server
    ortho = _cog(root / "o.tif", rng)
    with rasterio.open(ortho) as src:
        grid = dict(crs=src.crs, transform=src.transform)
    write_raster(root / "ndsm.tif", rng.uniform(0, 10, (96, 128)).astype(np.float32), **grid)
    code, out, err = run_cli(capsys, "tile", "--ortho", f"{url}/o.tif", "--ndsm", f"{url}/ndsm.tif",
                             "--size", "32", "--min-valid", "0.1", "--split-block", "16", "--out", tmp_path / "t",
                             "--quiet")
    assert code == 0, err
    assert "patches" in out and f"/vsicurl/{url}/o.tif" in (tmp_path / "t" / "dataset.yaml").read_text()
    code, out, err = run_cli(capsys, "tile", "--ortho", f"{url}/nope.tif", "--ndsm", f"{url}/ndsm.tif",
                             "--out", tmp_path / "t2", "--quiet")
    assert code == 1 and "cannot be opened" in err and not (tmp_path / "t2").exists()

    pred = write_prediction_folder(tmp_path / "pred", rng)
    write_raster(root / "ref.tif", rng.uniform(0, 20, (64, 64)).astype(np.float32))  # the prediction's grid
    code, out, err = run_cli(capsys, "evaluate", "--pred", pred, "--height", f"{url}/ref.tif", "--no-plots",
                             "--out", tmp_path / "eval" / "report.json", "--quiet")
    assert code == 0, err
    assert f"/vsicurl/{url}/ref.tif" in (tmp_path / "eval" / "report.json").read_text()
