"""One clean line for each case of issue 24's class 5: each names the input and the fix, never
`Error: unexpected ...` and never raw library lines."""

from __future__ import annotations

import csv
import dataclasses
import functools
import http.server
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from affine import Affine
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_prediction_folder, write_raster
from helpers.tilefolder import write_tile_folder
from helpers.tmpfs import mount_tmpfs
from test_outputs import ONE_THREAD
from test_remote import RangeHandler
from test_robustness import CRS, PREDICT, T05, assert_ok, no_final_outputs, rgb, tiny_train_yaml
from test_sanity import one_error_line

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.formats.prediction import NotAPredictionFolder, PredictionFolder
from aerialmtl.models.calibration import Calibration

run = run_cli


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    model, meta = tiny_d3net()
    path = tmp_path_factory.mktemp("m") / "m.pt"
    save_checkpoint(path, model, meta)
    return path


@pytest.mark.parametrize("url", ["s3://bucket/maps", "/vsis3/bucket/maps", "https://example.org/maps"])
def test_out_on_a_url_is_refused_and_nothing_local_is_made(tmp_path: Path, capsys, ckpt: Path, url: str,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    ortho = rgb(tmp_path)
    for args in (["predict", ortho, "--model", ckpt, "--out", url, *PREDICT],
                 ["tile", "--ortho", ortho, "--ndsm", ortho, "--out", url, "--quiet"]):
        one_error_line(run(capsys, *args), "Invalid value for '--out': outputs must be local", url,
                       "copy it up afterwards", code=2)
    assert sorted(os.listdir(tmp_path)) == ["ortho.tif"]  # no 's3:' or 'https:' folder


@pytest.mark.parametrize("content", ["[1, 2]", "null", '{"files": "height.tif"}', '{"files": {"height": 3}, '
                                     '"grid": {"width": "wide"}}', "{not json"])
def test_a_prediction_json_of_another_shape_is_not_a_prediction_folder(tmp_path: Path, capsys, ckpt: Path,
                                                                       content: str) -> None:
    pred = write_prediction_folder(tmp_path / "pred", np.random.default_rng(0))
    (pred / "prediction.json").write_text(content)
    with pytest.raises(NotAPredictionFolder, match="is not a prediction folder's prediction.json of aerialmtl"):
        PredictionFolder(pred).info()
    assert PredictionFolder(pred).check().startswith("its prediction.json is not aerialmtl's")
    assert PredictionFolder(pred).owned_files() == []  # nothing of it is ours to replace
    # predict --skip-existing: not a run of ours, so its files are not replaced without --overwrite
    ortho = rgb(tmp_path)
    one_error_line(run(capsys, "predict", ortho, "--model", ckpt, "--out", pred, *PREDICT, "--skip-existing"),
                   "already holds", "--overwrite")
    assert (pred / "prediction.json").read_text() == content
    assert_ok(run(capsys, "predict", ortho, "--model", ckpt, "--out", pred, *PREDICT, "--overwrite"))


def test_a_south_up_orthophoto_is_not_north_up(tmp_path: Path, capsys, ckpt: Path) -> None:
    img = np.random.default_rng(0).integers(1, 255, (3, 32, 32)).astype(np.uint8)
    ortho = write_raster(tmp_path / "s.tif", img, CRS, Affine(0.5, 0, 500000.0, 0, 0.5, 4999984.0))
    for args in (["predict", ortho, "--model", ckpt, "--out", tmp_path / "p", *PREDICT],
                 ["tile", "--ortho", ortho, "--ndsm", ortho, "--size", "32", "--out", tmp_path / "t", "--quiet"]):
        one_error_line(run(capsys, *args), f"orthophoto '{ortho}' is south-up", "not north-up", "gdalwarp")


@pytest.fixture
def full_fs(tmp_path: Path):
    yield from mount_tmpfs(tmp_path / "full", "size=200k")


def test_a_full_disk_while_predicting_is_one_line_without_libtiff_noise(tmp_path: Path, ckpt: Path,
                                                                        full_fs: Path) -> None:
    ortho = rgb(tmp_path, size=(512, 512))
    out = full_fs / "p"
    res = subprocess.run([sys.executable, "-m", "aerialmtl", "predict", str(ortho), "--model", str(ckpt), "--out",
                          str(out), *PREDICT[:-1], "--window", "256", "--quiet"], capture_output=True, text=True,
                         env=ONE_THREAD, timeout=300)
    assert res.returncode == 1, res
    assert res.stderr.strip().splitlines() == [
        f"Error: no space left on the device holding '{out}' while writing the prediction folder; free space there "
        f"or write to another folder (another --out); no partial file was left at '{out}'"]
    assert not out.exists() or not any(out.iterdir())


class _Dying(RangeHandler):
    """Answers the first ``keep`` range requests, then announces a range and closes after 10 bytes."""

    keep = 1
    served = 0

    def send_head(self):  # type: ignore[no-untyped-def]
        if self.headers.get("Range"):
            _Dying.served += 1
            if _Dying.served > _Dying.keep:
                self.send_response(206)
                self.send_header("Content-Length", "100000")
                self.send_header("Content-Range", "bytes 0-99999/9999999")
                self.end_headers()
                self.wfile.write(b"x" * 10)
                self.wfile.flush()
                self.connection.shutdown(socket.SHUT_RDWR)
                return None
        return super().send_head()


@pytest.fixture
def dying_server(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    root = tmp_path / "www"
    root.mkdir()
    _Dying.served = 0
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Dying, directory=str(root)))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", root
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_a_server_dying_mid_read_is_named(tmp_path: Path, capsys, ckpt: Path, dying_server: tuple[str, Path],
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    url, root = dying_server
    img = np.random.default_rng(0).integers(1, 255, (3, 1024, 1024)).astype(np.uint8)  # several 1 MiB chunks
    write_raster(root / "o.tif", img, CRS, T05, tiled=True, blockxsize=256, blockysize=256)
    monkeypatch.setenv("GDAL_HTTP_MAX_RETRY", "0")
    out = tmp_path / "p"
    one_error_line(run(capsys, "predict", f"{url}/o.tif", "--model", ckpt, "--out", out, "--mc", "1", "--window", "256",
                       "--quiet"), f"orthophoto '{url}/o.tif' could not be read after it was opened (GDAL: ",
                   "check the network and the server, then re-run")
    assert no_final_outputs(out)


def test_a_hung_server_is_named(tmp_path: Path, capsys, ckpt: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    hung = socket.socket()
    hung.bind(("127.0.0.1", 0))
    hung.listen(8)  # connections are accepted by the kernel, never answered
    monkeypatch.setenv("GDAL_HTTP_TIMEOUT", "2")
    monkeypatch.setenv("GDAL_HTTP_MAX_RETRY", "0")
    url = f"http://127.0.0.1:{hung.getsockname()[1]}/o.tif"
    try:
        t0 = time.monotonic()
        line = one_error_line(run(capsys, "predict", url, "--model", ckpt, "--out", tmp_path / "p", *PREDICT),
                              f"orthophoto '/vsicurl/{url}' cannot be opened", "check the URL and the network")
    finally:
        hung.close()
    assert "timed out" in line or "did not answer within 2 s" in line, line
    assert "not recognized as" not in line and time.monotonic() - t0 < 60


def test_a_model_from_the_environment_is_named_as_such(tmp_path: Path, capsys,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AERIALMTL_MODEL", str(tmp_path / "gone.pt"))
    one_error_line(run(capsys, "predict", rgb(tmp_path), *PREDICT), f"checkpoint '{tmp_path / 'gone.pt'}' does not "
                   "exist", "comes from the AERIALMTL_MODEL environment variable", "or pass --model")


def test_a_truncated_training_patch_is_named(tmp_path: Path, capsys) -> None:
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 3, "val": 1})
    patch = sorted((tiles / "train" / "image").glob("*.tif"))[1]
    patch.write_bytes(patch.read_bytes()[: patch.stat().st_size // 2])
    one_error_line(run(capsys, "train", "--config", tiny_train_yaml(tmp_path / "c.yaml"), "--data", tiles, "--out",
                       tmp_path / "run", "--max-steps", "1", "--quiet"), f"patch '{patch}'", "truncated or damaged",
                   "aerialmtl tile")


@pytest.mark.parametrize(("x", "y", "needle"), [
    ((0.0, 10.0), (-5.0, -1.0), "its height map sends every height below 0 m (to -1 m at most"),
])
def test_an_edited_calibration_is_refused_unless_switched_off(tmp_path: Path, capsys, x: tuple, y: tuple,
                                                              needle: str) -> None:
    model, meta = tiny_d3net()
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, dataclasses.replace(meta, calibration=Calibration(x, y)))
    ortho = rgb(tmp_path)
    one_error_line(run(capsys, "predict", ortho, "--model", path, "--out", tmp_path / "p", *PREDICT),
                   f"checkpoint '{path}' has an invalid calibration: {needle}", "--no-calibration")
    assert_ok(run(capsys, "predict", ortho, "--model", path, "--out", tmp_path / "p", *PREDICT, "--no-calibration"))


@pytest.mark.parametrize(("y", "needle"), [((0.0, 8.0, 3.0), "non-decreasing"), ((0.0, 5.0, 1e6), "leave the")])
def test_a_calibration_no_model_can_have_refuses_the_checkpoint(tmp_path: Path, capsys, y: tuple,
                                                                needle: str) -> None:
    """A height map edited to decrease, or to reach heights no surface has, is not a calibration aerialmtl writes:
    the checkpoint is refused at load with one line naming it (the schema of issue 40), --no-calibration or not.
    """
    import torch

    model, meta = tiny_d3net()
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, dataclasses.replace(meta, calibration=Calibration((0.0, 5.0, 10.0), (0.0, 5.0, 10.0))))
    payload = torch.load(path, weights_only=True)
    payload["meta"]["calibration"]["height_y"] = list(y)
    torch.save(payload, path)
    for extra in ((), ("--no-calibration",)):
        one_error_line(run(capsys, "predict", rgb(tmp_path), "--model", path, "--out", tmp_path / "p", *PREDICT,
                           *extra), f"checkpoint '{path}'", needle)


def test_a_vrt_with_a_missing_source_names_it(tmp_path: Path, capsys, ckpt: Path) -> None:
    vrt = tmp_path / "o.vrt"
    vrt.write_text(f"""<VRTDataset rasterXSize="32" rasterYSize="32"><SRS>{CRS}</SRS>
<GeoTransform>500000, 0.5, 0, 5000000, 0, -0.5</GeoTransform>""" + "".join(
        f"""<VRTRasterBand dataType="Byte" band="{b}"><SimpleSource><SourceFilename relativeToVRT="1">gone.tif
</SourceFilename><SourceBand>{b}</SourceBand></SimpleSource></VRTRasterBand>""".replace("\n", "") for b in (1, 2, 3))
        + "</VRTDataset>")
    one_error_line(run(capsys, "predict", vrt, "--model", ckpt, "--out", tmp_path / "p", *PREDICT),
                   f"orthophoto '{vrt}' could not be read: a source file it lists is missing", "gdalbuildvrt")


def test_a_zip_path_with_a_missing_archive_or_member_names_which(tmp_path: Path, capsys, ckpt: Path) -> None:
    import zipfile

    with zipfile.ZipFile(tmp_path / "a.zip", "w") as z:
        z.write(rgb(tmp_path), "o.tif")
    one_error_line(run(capsys, "predict", f"/vsizip/{tmp_path}/gone.zip/o.tif", "--model", ckpt, "--out",
                       tmp_path / "p", *PREDICT), "no archive file was found along this path")
    one_error_line(run(capsys, "predict", f"/vsizip/{tmp_path}/a.zip/x.tif", "--model", ckpt, "--out",
                       tmp_path / "p", *PREDICT), f"the archive '{tmp_path}/a.zip' holds no raster 'x.tif'", "unzip -l")


def test_the_calibration_of_a_flat_area_is_not_refused(tmp_path: Path, capsys) -> None:
    """A run on a flat area (every reference height 0 m) fits a map to 0 m: a real fit, predicted as it is."""
    model, meta = tiny_d3net()
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, dataclasses.replace(meta, height_range=(0.0, 0.0),
                                                     calibration=Calibration((0.0, 3.0), (0.0, 0.0))))
    assert_ok(run(capsys, "predict", rgb(tmp_path), "--model", path, "--out", tmp_path / "p", *PREDICT))


# ---- issue 38: which number is which, every file named -----------------------------------------------
def test_train_says_which_validation_belongs_to_best_pt(tmp_path: Path, capsys) -> None:
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 4, "val": 2})
    code, out, err = run(capsys, "train", "--config", tiny_train_yaml(tmp_path / "c.yaml"), "--data", tiles, "--out",
                         tmp_path / "run", "--max-steps", "4", "--quiet")
    assert code == 0, err
    lines = out.splitlines()
    stopped = next(line for line in lines if line.startswith("stopped by"))
    best = next(line for line in lines if line.startswith("best checkpoint:"))
    assert "last validation (step 4, last.pt): height MAE " in stopped and " m, RMSE " in stopped
    assert f"{tmp_path / 'run' / 'best.pt'} (the lowest validation score of the run: step " in best
    assert "height MAE " in best
    # the step named is a validation row of log.csv with that MAE
    step = int(best.split("step ")[1].split(",")[0])
    mae = best.split("height MAE ")[1].split(" m")[0]
    with open(tmp_path / "run" / "log.csv", newline="") as f:
        (row,) = [r for r in csv.DictReader(f) if r["kind"] == "val" and int(r["step"]) == step]
    assert f"{float(row['height_mae']):.4g}" == mae


def test_predict_lists_every_file_it_wrote(tmp_path: Path, capsys, ckpt: Path) -> None:
    out = tmp_path / "p"
    code, stdout, err = run(capsys, "predict", rgb(tmp_path), "--model", ckpt, "--out", out, *PREDICT)
    assert code == 0, err
    listed = stdout.split("files: ")[1].split("\n")[0].split(", ")
    assert sorted(listed) == sorted(p.name for p in out.iterdir())
    assert {"height.qml", "item.json", "prediction.json"} <= set(listed)
