"""Provenance is taken when the bytes are read (issue 24, part 1): the checkpoint's hash is that of the bytes
loaded, an orthophoto changed under a run is refused, a VRT's fingerprint covers its sources, a zip its
archive, an HTTP input what the server says (ETag, Last-Modified, size), and `--skip-existing` removes the
mosaics of layers a run no longer makes."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_raster
from test_outputs import ONE_THREAD, _wait_for
from test_remote import server  # noqa: F401 - the local HTTP server fixture
from test_robustness import CRS, PREDICT, T05, no_final_outputs, rgb

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.inference.predict import Predictor, predict_raster
from aerialmtl.io.fingerprint import input_fingerprint

run = run_cli


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("ckpts")
    paths = []
    for k in (0, 1):
        model, meta = tiny_d3net()
        with torch.no_grad():
            next(model.parameters()).add_(0.05 * k)
        paths.append(folder / f"m{k}.pt")
        save_checkpoint(paths[-1], model, meta)
    return paths[0], paths[1]


CHANGED = "it was made with another or a changed orthophoto"


def _sha(path: Path) -> str:
    return "sha256:" + hashlib.sha256(path.read_bytes()).hexdigest()


def _provenance(out: Path) -> dict:
    return json.loads((out / "prediction.json").read_text())["provenance"]


def _skip(capsys, ortho: object, ckpt: Path, out: Path, *extra: object) -> str:
    rc, stdout, err = run(capsys, "predict", ortho, "--model", ckpt, "--out", out, *PREDICT, "--skip-existing", *extra)
    assert rc == 0, (stdout, err)
    return stdout.strip().splitlines()[-1]


def test_the_checkpoint_hash_is_that_of_the_bytes_loaded(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    """`train` replacing RUN/best.pt while predict runs: the maps are recorded as the old model's."""
    best = tmp_path / "best.pt"
    shutil.copy(ckpts[0], best)
    predictor = Predictor(best, mc=2, window=32, overlap=0, precision="fp32", engine="torch")
    shutil.copy(ckpts[1], tmp_path / ".best.pt.partial")
    os.replace(tmp_path / ".best.pt.partial", best)  # as save_checkpoint replaces it
    ortho, out = rgb(tmp_path), tmp_path / "pred"
    predict_raster(ortho, predictor, out, progress=False)  # the model loaded above
    assert _provenance(out)["checkpoint"] == _sha(ckpts[0]) != _sha(best)
    assert _skip(capsys, ortho, best, out).endswith("it was made with another model")  # not kept for good
    assert _provenance(out)["checkpoint"] == _sha(best)


def test_an_orthophoto_replaced_during_the_run_is_refused(tmp_path: Path, ckpts: tuple[Path, Path]) -> None:
    """A sync job replacing the orthophoto while predict reads it (real processes): no maps are committed."""
    ortho = rgb(tmp_path, size=(256, 256), seed=1)
    newer = rgb(tmp_path, name="newer.tif", size=(256, 256), seed=2)
    out = tmp_path / "pred"
    cmd = [sys.executable, "-m", "aerialmtl", "predict", str(ortho), "--model", str(ckpts[0]), "--out", str(out),
           "--mc", "8", "--window", "64", "--overlap", "16", "--batch-size", "1", "--precision", "fp32", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ONE_THREAD)
    try:
        _wait_for(lambda: out.is_dir() and any(p.name.endswith(".staging") for p in out.iterdir()), proc,
                  "the first staging file")
        os.replace(newer, ortho)  # what rsync / a sync client does
        _, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:  # pragma: no cover
            proc.kill()
            proc.communicate()
    lines = stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1, stderr
    assert lines[0].startswith(f"Error: orthophoto '{ortho}' changed while it was read (")
    assert "re-run when the file is no longer being written or replaced" in lines[0]
    assert no_final_outputs(out) and not out.exists()  # the folder it created is gone again


def _vrt(path: Path, source: Path, width: int, height: int) -> Path:
    path.write_text(f"""<VRTDataset rasterXSize="{width}" rasterYSize="{height}">
  <SRS>{CRS}</SRS><GeoTransform>{T05.c}, {T05.a}, 0, {T05.f}, 0, {T05.e}</GeoTransform>
""" + "".join(f"""  <VRTRasterBand dataType="Byte" band="{b}"><SimpleSource>
    <SourceFilename relativeToVRT="1">{source.name}</SourceFilename><SourceBand>{b}</SourceBand>
  </SimpleSource></VRTRasterBand>
""" for b in (1, 2, 3)) + "</VRTDataset>\n")
    return path


def test_a_vrt_fingerprint_covers_its_sources(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    src = rgb(tmp_path, name="src.tif")
    vrt = _vrt(tmp_path / "o.vrt", src, 64, 64)
    fp = input_fingerprint(vrt)
    assert fp["sources"] == [{"path": str(src.resolve()), "size": src.stat().st_size,
                              "mtime_ns": src.stat().st_mtime_ns, "sidecars": {}}]
    out = tmp_path / "pred"
    _skip(capsys, vrt, ckpts[0], out)
    assert _skip(capsys, vrt, ckpts[0], out).endswith("(same model, settings, input)")
    rgb(tmp_path, name="src.tif", seed=9)  # a new survey of the same grid, the VRT untouched
    assert _skip(capsys, vrt, ckpts[0], out).rsplit(": ", 1)[-1].startswith(CHANGED)


def test_a_zip_input_is_fingerprinted_by_its_archive(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    def deliver(seed: int) -> None:
        tif = rgb(tmp_path, name="o.tif", seed=seed)
        with zipfile.ZipFile(tmp_path / "area.zip", "w") as z:
            z.write(tif, "o.tif")

    deliver(1)
    path, out = f"/vsizip/{tmp_path / 'area.zip'}/o.tif", tmp_path / "pred"
    _skip(capsys, path, ckpts[0], out)
    assert _provenance(out)["input"]["archive"]["path"] == str(tmp_path / "area.zip")
    assert _skip(capsys, path, ckpts[0], out).endswith("(same model, settings, input)")
    deliver(2)  # a new delivery of the same grid
    assert _skip(capsys, path, ckpts[0], out).rsplit(": ", 1)[-1].startswith(CHANGED)


def test_an_http_input_records_what_the_server_says(tmp_path: Path, capsys, ckpts: tuple[Path, Path],
                                                    server: tuple[str, Path]) -> None:  # noqa: F811
    url, root = server
    rgb(root, name="o.tif", seed=1)
    out = tmp_path / "pred"
    _skip(capsys, f"{url}/o.tif", ckpts[0], out)
    fp = _provenance(out)["input"]
    assert fp["server"]["size"] == (root / "o.tif").stat().st_size and fp["server"]["last_modified"]
    assert _skip(capsys, f"{url}/o.tif", ckpts[0], out).endswith("(same model, settings, input)")
    rgb(root, name="o.tif", seed=2)  # same size and grid, other pixels, a newer Last-Modified
    st = (root / "o.tif").stat()
    os.utime(root / "o.tif", (st.st_atime, st.st_mtime + 5))
    assert _skip(capsys, f"{url}/o.tif", ckpts[0], out).rsplit(": ", 1)[-1].startswith(CHANGED)


def test_skip_existing_removes_the_mosaics_of_layers_no_longer_made(tmp_path: Path, capsys,
                                                                    ckpts: tuple[Path, Path]) -> None:
    a, b = rgb(tmp_path, name="a.tif", seed=1), rgb(tmp_path, name="b.tif", seed=2)
    out = tmp_path / "maps"
    rc, _, err = run(capsys, "predict", a, b, "--model", ckpts[0], "--out", out, *PREDICT)
    assert rc == 0, err
    assert (out / "height_std.mosaic.vrt").is_file() and (out / "height_std.mosaic.qml").is_file()
    (out / "notes.mosaic.vrt").write_text("mine")
    rc, _, err = run(capsys, "predict", a, b, "--model", ckpts[0], "--out", out, *PREDICT, "--mc", "1",
                     "--skip-existing")
    assert rc == 0, err
    assert not (out / "a" / "height_std.tif").exists()
    assert not (out / "height_std.mosaic.vrt").exists() and not (out / "height_std.mosaic.qml").exists()
    assert (out / "height.mosaic.vrt").is_file() and (out / "notes.mosaic.vrt").read_text() == "mine"
    assert "height_std" not in (out / "collection.json").read_text()


def test_an_unchanged_input_passes_the_check_after_reading(tmp_path: Path, ckpts: tuple[Path, Path]) -> None:
    ortho = write_raster(tmp_path / "o.tif", np.full((3, 40, 40), 100, np.uint8), CRS, T05)
    predictor = Predictor(ckpts[0], mc=1, window=32, overlap=0, precision="fp32")
    src = predictor.open(ortho)
    assert src.changed() is None
    os.utime(ortho, ns=(0, 10**9))
    assert "mtime_ns" in (src.changed() or "")
