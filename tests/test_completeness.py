"""Complete means verified: ``--skip-existing`` skips a prediction folder only when its ``prediction.json``
records the same model, settings and input and every layer is whole; anything else is recomputed and the
summary says why. Two predict processes on one ``--out``: the second is refused (issue 18, parts 2, 3, 5)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from test_outputs import ONE_THREAD, _wait_for
from test_robustness import PREDICT, assert_error, assert_ok, no_final_outputs, rgb

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.formats.prediction import PredictionFolder
from aerialmtl.io.fingerprint import input_fingerprint
from aerialmtl.io.outputs import LOCK_FILE

run = run_cli


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two tiny checkpoints with different weights."""
    folder = tmp_path_factory.mktemp("ckpts")
    import torch

    paths = []
    for k in (0, 1):
        model, meta = tiny_d3net()
        with torch.no_grad():
            next(model.parameters()).add_(0.01 * k)  # the second model's weights differ
        paths.append(folder / f"m{k}.pt")
        save_checkpoint(paths[-1], model, meta)
    return paths[0], paths[1]


def _predict(capsys, ortho: Path, ckpt: Path, out: Path, *extra: object) -> list[str]:
    args = ["predict", ortho, "--model", ckpt, "--out", out, *PREDICT, "--skip-existing", *extra]
    rc, stdout, err = run(capsys, *args)
    assert rc == 0, (stdout, err)
    return stdout.strip().splitlines()


def test_skip_existing_skips_only_a_verified_folder(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    ortho, out = rgb(tmp_path, size=(64, 64)), tmp_path / "pred"
    _predict(capsys, ortho, ckpts[0], out)
    info = json.loads((out / "prediction.json").read_text())
    prov = info["provenance"]
    assert prov["checkpoint"].startswith("sha256:") and prov["settings"]["mc_samples"] == 2
    assert prov["input"]["path"] == str(ortho.resolve()) and prov["input"]["size"] == ortho.stat().st_size
    # every layer's size (the .qml styles and item.json are the user's to edit)
    assert set(info["file_sizes"]) == {n for n in info["files"].values() if n.endswith(".tif")}

    assert _predict(capsys, ortho, ckpts[0], out)[-1].endswith("skipped, its prediction folder is complete "
                                                                "(same model, settings, input)")
    # another --mc: recomputed (its own outputs replaced without --overwrite), and the summary says why
    lines = _predict(capsys, ortho, ckpts[0], out, "--mc", "3")
    assert "recomputed" in lines[-1] and "mc_samples 2 → 3" in lines[-1], lines
    assert json.loads((out / "prediction.json").read_text())["mc_samples"] == 3
    # another model
    lines = _predict(capsys, ortho, ckpts[1], out, "--mc", "3")
    assert lines[-1].endswith("it was made with another model"), lines
    # a truncated layer
    data = (out / "height.tif").read_bytes()
    (out / "height.tif").write_bytes(data[: len(data) // 2])
    lines = _predict(capsys, ortho, ckpts[1], out, "--mc", "3")
    assert "height.tif is truncated or was changed" in lines[-1], lines
    # the orthophoto changed since (its mtime)
    st = ortho.stat()
    os.utime(ortho, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    lines = _predict(capsys, ortho, ckpts[1], out, "--mc", "3")
    assert "it was made with another or a changed orthophoto (mtime_ns" in lines[-1], lines
    assert PredictionFolder(out).is_complete() and sorted(p.name for p in out.iterdir() if p.name[0] == ".") == []


def test_skip_existing_never_replaces_files_no_run_wrote(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    out = tmp_path / "pred"
    out.mkdir()
    (out / "height.tif").write_text("precious")
    res = run(capsys, "predict", rgb(tmp_path), "--model", ckpts[0], "--out", out, *PREDICT, "--skip-existing")
    assert_error(res, "already holds height.tif", "--overwrite")
    assert (out / "height.tif").read_text() == "precious"


def test_a_hand_edited_invalid_prediction_json_is_named_as_the_reason(tmp_path: Path, capsys,
                                                                       ckpts: tuple[Path, Path]) -> None:
    """A prediction.json no schema accepts owns nothing, so --skip-existing must refuse the folder; the refusal
    says that the file is why (it said only 'already holds ...; pass --overwrite')."""
    out = tmp_path / "pred"
    ortho = rgb(tmp_path)
    _predict(capsys, ortho, ckpts[0], out)
    info = json.loads((out / "prediction.json").read_text())
    info["file_sha256"] = ["not", "a", "mapping"]
    (out / "prediction.json").write_text(json.dumps(info))
    before = (out / "height.tif").read_bytes()
    res = run(capsys, "predict", ortho, "--model", ckpts[0], "--out", out, *PREDICT, "--skip-existing")
    assert_error(res, "already holds height.tif", "--overwrite", "--skip-existing could not tell them finished",
                 "prediction.json")
    assert (out / "height.tif").read_bytes() == before


def test_a_users_style_or_stac_item_in_out_is_never_replaced_without_overwrite(
        tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    """height.qml (QGIS's 'save as default' style) and item.json are outputs too: a user's own are refused
    like a user's height.tif, with and without --skip-existing (they were replaced silently, exit 0)."""
    out = tmp_path / "pred"
    out.mkdir()
    (out / "height.qml").write_text("<qgis mine='1'/>")
    (out / "item.json").write_text('{"mine": 1}')
    for extra in ((), ("--skip-existing",)):
        res = run(capsys, "predict", rgb(tmp_path), "--model", ckpts[0], "--out", out, *PREDICT, *extra)
        assert_error(res, "already holds height.qml, item.json", "--overwrite")
        assert (out / "height.qml").read_text() == "<qgis mine='1'/>"
        assert (out / "item.json").read_text() == '{"mine": 1}'
    assert not (out / "height.tif").exists()


def test_a_layer_that_does_not_open_is_not_complete(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    out = tmp_path / "pred"
    _predict(capsys, rgb(tmp_path), ckpts[0], out)
    info = json.loads((out / "prediction.json").read_text())
    del info["file_sizes"]  # as an older version wrote it: the layers are opened instead
    (out / "prediction.json").write_text(json.dumps(info))
    assert PredictionFolder(out).check() is None
    (out / "classes.tif").write_bytes(b"not a tiff")
    assert PredictionFolder(out).check().startswith("classes.tif does not open")


def test_remote_input_fingerprint_needs_no_stat() -> None:
    raster = {"width": 10, "height": 20, "transform": [0.5, 0.0, 1.0, 0.0, -0.5, 2.0], "crs": "EPSG:32631",
              "nodata": [None]}
    fp = input_fingerprint("http://127.0.0.1:9/o.tif", raster)
    assert fp == {"path": "/vsicurl/http://127.0.0.1:9/o.tif", "raster": raster}


@pytest.mark.slow
def test_two_predict_processes_on_one_out_then_sigterm(tmp_path: Path, ckpts: tuple[Path, Path]) -> None:
    """The second predict on a busy --out fails naming the first's PID and touches nothing; SIGTERM then
    stops the first like Ctrl-C: exit 143, its message, no output and no folder left."""
    ortho = rgb(tmp_path, size=(1024, 1024), seed=3)  # a minute of work or more: stopped long before its end
    out = tmp_path / "pred"
    cmd = [sys.executable, "-m", "aerialmtl", "predict", str(ortho), "--model", str(ckpts[0]), "--out", str(out),
           "--mc", "16", "--window", "64", "--overlap", "16", "--batch-size", "1", "--precision", "fp32", "--quiet"]
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ONE_THREAD)
    try:
        _wait_for(lambda: out.is_dir() and any(p.name.endswith(".staging") for p in out.iterdir()), first,
                  "the first staging file")
        second = subprocess.run(cmd + ["--overwrite"], capture_output=True, text=True, env=ONE_THREAD, timeout=300)
        assert second.returncode == 1, second
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and f"is in use by aerialmtl predict (PID {first.pid} " in lines[0], lines
        assert first.poll() is None, "the first run ended before the signal; use a larger raster"
        first.send_signal(signal.SIGTERM)
        _, stderr = first.communicate(timeout=120)
    finally:
        if first.poll() is None:  # pragma: no cover - only when an assertion above failed
            first.kill()
            first.communicate()
    assert first.returncode == 143, stderr
    assert stderr.strip().splitlines() == [
        "Error: interrupted; no output was left at a final path. Re-run the command to finish."]
    assert no_final_outputs(out) and not out.exists()


def test_a_held_folder_is_refused_before_any_work(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    from test_outputs import _hold_lock

    out = tmp_path / "pred"
    out.mkdir()
    holder = _hold_lock(out, "evaluate")
    try:
        res = run(capsys, "predict", rgb(tmp_path), "--model", ckpts[0], "--out", out, *PREDICT)
        assert_error(res, f"in use by aerialmtl evaluate (PID {holder.pid} ")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE]
    finally:
        holder.kill()
        holder.wait()
    assert_ok(run(capsys, "predict", rgb(tmp_path), "--model", ckpts[0], "--out", out, *PREDICT))


@pytest.mark.slow
def test_torchrun_job_shares_the_lock_and_a_busy_folder_stops_every_rank(tmp_path: Path,
                                                                         ckpts: tuple[Path, Path]) -> None:
    """Rank 0 holds the folder for the job (the ranks of one job never refuse each other: see
    test_predict_distributed); when another process holds it, every rank stops with the holder's PID."""
    from test_outputs import _hold_lock

    out = tmp_path / "pred"
    out.mkdir()
    holder = _hold_lock(out, "predict")
    try:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m",
               "aerialmtl", "predict", str(rgb(tmp_path, size=(96, 96))), "--model", str(ckpts[0]), "--out",
               str(out), *PREDICT]
        res = subprocess.run(cmd, capture_output=True, text=True, env=ONE_THREAD, timeout=600)
    finally:
        holder.kill()
        holder.wait()
    assert res.returncode != 0
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error: ")]
    assert sorted(e.split("]")[0] for e in errors) == ["Error: [rank 0", "Error: [rank 1"], res.stderr
    assert all(f"in use by aerialmtl predict (PID {holder.pid} " in e for e in errors), errors
    assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE]


def test_predict_into_the_folder_of_its_input_is_refused(tmp_path: Path, capsys, ckpts: tuple[Path, Path]) -> None:
    ortho = rgb(tmp_path)
    res = run(capsys, "predict", ortho, "--model", ckpts[0], "--out", tmp_path, *PREDICT)
    assert_error(res, "--out", f"contains the input ORTHOS '{ortho}'", code=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ortho.tif"]
