"""`aerialmtl --progress json`: one JSON line per step on stderr, for programs that run the command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli, tiny_d3net, write_raster

from aerialmtl import progress
from aerialmtl.formats.checkpoint import save_checkpoint


def _json_lines(text: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def test_json_bar_counts_updates_and_iterations(capsys: pytest.CaptureFixture) -> None:
    previous = progress.set_mode("json")
    try:
        with progress.tqdm(total=3, desc="train", unit="step", initial=1) as bar:
            bar.update(1)
            bar.update(1)
        assert list(progress.tqdm_auto(iter("ab"), desc="tiling", unit="patch")) == ["a", "b"]
        assert list(progress.tqdm(["x"], desc="off", disable=True)) == ["x"]
    finally:
        progress.set_mode(previous)
    captured = capsys.readouterr()
    assert _json_lines(captured.err) == [
        {"stage": "train", "done": 1, "total": 3, "unit": "step"},
        {"stage": "train", "done": 2, "total": 3, "unit": "step"},
        {"stage": "train", "done": 3, "total": 3, "unit": "step"},
        {"stage": "tiling", "done": 0, "total": None, "unit": "patch"},
        {"stage": "tiling", "done": 1, "total": None, "unit": "patch"},
        {"stage": "tiling", "done": 2, "total": None, "unit": "patch"},
    ]
    assert captured.err.count("\n") == 6 and captured.out == ""  # no bar drawn, nothing else written


def test_unknown_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="bar, json"):
        progress.set_mode("xml")


@pytest.fixture
def model_and_ortho(tmp_path: Path) -> tuple[Path, Path]:
    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "m.pt", model, meta)
    rng = np.random.default_rng(0)
    ortho = write_raster(tmp_path / "ortho.tif", rng.integers(0, 255, (3, 96, 96)).astype(np.uint8))
    return tmp_path / "m.pt", ortho


def test_predict_reports_every_window_as_json(model_and_ortho: tuple[Path, Path], tmp_path: Path,
                                              capsys: pytest.CaptureFixture) -> None:
    model, ortho = model_and_ortho
    code, out, err = run_cli(capsys, "--progress", "json", "predict", ortho, "--model", model, "--out",
                             tmp_path / "p", "--mc", "2", "--tile", "64", "--overlap", "16")
    assert code == 0, err
    lines = _json_lines(err)
    assert lines[0] == {"stage": "ortho.tif", "done": 0, "total": 4, "unit": "win"}
    assert [line["done"] for line in lines] == sorted(line["done"] for line in lines)  # never goes back
    assert lines[-1]["done"] == lines[-1]["total"] == 4
    assert "ortho.tif → " in out and not _json_lines(out)  # the result line is unchanged, on stdout
    assert progress.get_mode() == "bar"  # the option held for that command only

    # the default draws a bar, no JSON; --quiet silences JSON too
    code, _, err = run_cli(capsys, "predict", ortho, "--model", model, "--out", tmp_path / "q", "--mc", "2",
                           "--tile", "64", "--overlap", "16")
    assert code == 0 and not _json_lines(err) and "win" in err
    code, _, err = run_cli(capsys, "--progress", "json", "predict", ortho, "--model", model, "--out",
                           tmp_path / "r", "--mc", "2", "--tile", "64", "--overlap", "16", "--quiet")
    assert code == 0 and not _json_lines(err)


def test_progress_mode_from_the_environment(model_and_ortho: tuple[Path, Path], tmp_path: Path,
                                            capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """AERIALMTL_PROGRESS=json reaches processes whose command line the caller does not write (torchrun)."""
    model, ortho = model_and_ortho
    monkeypatch.setenv(progress.PROGRESS_ENV, "json")
    code, _, err = run_cli(capsys, "predict", ortho, "--model", model, "--out", tmp_path / "p", "--mc", "1",
                           "--tile", "64", "--overlap", "16")
    assert code == 0, err
    assert _json_lines(err)[-1] == {"stage": "ortho.tif", "done": 4, "total": 4, "unit": "win"}
