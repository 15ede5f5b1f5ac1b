"""The OpenVINO engine's cache heals: a corrupt entry (truncated, zero-filled, edited) is rebuilt with a warning
and never loaded; a cache folder that is full or read-only means a prediction without caching, never a crash."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_raster
from helpers.tmpfs import mount_tmpfs

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.stores import CorruptEntry, pack, unpack

pytest.importorskip("openvino")


def test_entries_carry_their_checksum() -> None:
    data = pack([b"<xml/>", b"\x01\x02\x03" * 100])
    assert unpack(data) == [b"<xml/>", b"\x01\x02\x03" * 100]
    for bad in (data[:-1], bytes(len(data)), data[:-5] + b"\x00" * 5, data[:10]):
        with pytest.raises(CorruptEntry):
            unpack(bad)


@pytest.fixture
def predict_setup(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, Path]:
    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "m.pt", model, meta)
    ortho = write_raster(tmp_path / "o.tif", rng.integers(1, 256, size=(3, 48, 64)).astype(np.uint8))
    return tmp_path / "m.pt", ortho


def _predict(capsys: pytest.CaptureFixture, ckpt: Path, ortho: Path, out: Path, cache: Path,
             monkeypatch: pytest.MonkeyPatch) -> tuple[int, str, np.ndarray]:
    """`aerialmtl predict` on the OpenVINO engine (named: ``auto`` takes torch for a job this small on a cold cache
    where the CPU kind's speedup was measured), cache at ``cache``."""
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(cache))
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", out, "--mc", "2", "--window", "64",
                           "--overlap", "16", "--engine", "openvino")
    assert code == 0, err
    assert json.loads((out / "prediction.json").read_text())["engine"] == "openvino"
    with rasterio.open(out / "height.tif") as src:
        return code, err, src.read(1)


def test_corrupt_entries_are_rebuilt_not_loaded(predict_setup: tuple[Path, Path], tmp_path: Path,
                                                capsys: pytest.CaptureFixture,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt, ortho = predict_setup
    cache = tmp_path / "cache"
    _, err, first = _predict(capsys, ckpt, ortho, tmp_path / "a", cache, monkeypatch)
    assert "warning" not in err.lower()
    entries = sorted(p for p in cache.rglob("*") if p.is_file())
    irs = [p for p in entries if p.suffix == ".ir"]
    blobs = [p for p in entries if p.suffix == ".blob"]
    assert irs and blobs and not [p for p in entries if p.name.startswith(".")]  # no staging file left
    # the second run loads everything from the cache: the same maps, no warning
    _, err, again = _predict(capsys, ckpt, ortho, tmp_path / "b", cache, monkeypatch)
    assert "warning" not in err.lower()
    np.testing.assert_array_equal(again, first)
    # what a power loss leaves (zero-filled, same size), a truncated file, an edited byte
    irs[0].write_bytes(bytes(irs[0].stat().st_size))
    blobs[0].write_bytes(blobs[0].read_bytes()[: blobs[0].stat().st_size // 2])
    data = bytearray(irs[-1].read_bytes())
    data[-100] ^= 0xFF
    irs[-1].write_bytes(bytes(data))
    _, err, healed = _predict(capsys, ckpt, ortho, tmp_path / "c", cache, monkeypatch)
    np.testing.assert_array_equal(healed, first)  # not all-zero heights from a zeroed IR
    for path in (irs[0], blobs[0], irs[-1]):
        assert f"cached OpenVINO model '{path}' is corrupt" in " ".join(err.split()) and "rebuilding it" in err
    # rebuilt: the next run is silent again
    _, err, _ = _predict(capsys, ckpt, ortho, tmp_path / "d", cache, monkeypatch)
    assert "warning" not in err.lower()


@pytest.fixture
def full_fs(tmp_path: Path):
    yield from mount_tmpfs(tmp_path / "full", "size=256k")


@pytest.fixture
def read_only_fs(tmp_path: Path):
    yield from mount_tmpfs(tmp_path / "ro", "ro,size=256k")


def test_full_cache_folder_predicts_without_caching(predict_setup: tuple[Path, Path], tmp_path: Path, full_fs: Path,
                                                    capsys: pytest.CaptureFixture,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt, ortho = predict_setup
    with warnings.catch_warnings():
        (full_fs / "filler").write_bytes(b"\0" * (256 * 1024 - 8 * 1024))
    _, err, heights = _predict(capsys, ckpt, ortho, tmp_path / "a", full_fs / "cache", monkeypatch)
    line = " ".join(err.split())
    assert f"the OpenVINO cache folder '{full_fs / 'cache'}" in line and "No space left" in line
    assert "AERIALMTL_OPENVINO_CACHE" in line and line.count("OpenVINO cache folder") == 1  # one warning
    assert "iostream" not in err and "unexpected" not in err
    _, _, reference = _predict(capsys, ckpt, ortho, tmp_path / "b", tmp_path / "ok", monkeypatch)
    np.testing.assert_array_equal(heights, reference)
    assert not [p for p in full_fs.rglob(".*") if p.is_file()]  # no staging file left on the full disk


def test_read_only_cache_folder_predicts_without_caching(predict_setup: tuple[Path, Path], tmp_path: Path,
                                                         read_only_fs: Path, capsys: pytest.CaptureFixture,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt, ortho = predict_setup
    _, err, _ = _predict(capsys, ckpt, ortho, tmp_path / "a", read_only_fs / "cache", monkeypatch)
    line = " ".join(err.split())
    assert f"the OpenVINO cache folder '{read_only_fs / 'cache'}/" in line
    assert "' cannot be written (Read-only file system); predicting without caching" in line


# ---- the warm path: a cached engine needs no torch model (aerialmtl.inference.model_record) ----------------------
def _outputs(out: Path) -> tuple[dict[str, bytes], dict]:
    """Every layer's bytes, and prediction.json without what differs from run to run (timings, creation time)."""
    files = {p.name: p.read_bytes() for p in sorted(out.glob("*.tif"))}
    info = json.loads((out / "prediction.json").read_text())
    info.pop("timings_s")
    return files, {k: v for k, v in info.items() if k not in ("created", "created_utc")}


def _no_loading(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make any load of a checkpoint's weights fail the test."""
    import aerialmtl.formats.checkpoint as checkpoint

    def refuse(*_: object, **__: object) -> None:
        raise AssertionError("the warm path loaded the checkpoint")

    monkeypatch.setattr(checkpoint, "read_model", refuse)


@pytest.mark.parametrize("mc", [1, 2])
def test_warm_cache_predicts_without_the_torch_model(predict_setup: tuple[Path, Path], tmp_path: Path, mc: int,
                                                     capsys: pytest.CaptureFixture,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The second run reads the checkpoint's record and the compiled models, never the weights, and writes the
    same bytes in every layer and the same prediction.json (timings and creation time aside): tolerance 0."""
    ckpt, ortho = predict_setup
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(tmp_path / "cache"))
    args = ("predict", ortho, "--model", ckpt, "--mc", mc, "--window", "64", "--overlap", "16", "--probabilities",
            "--engine", "openvino")  # named: auto takes torch for a job this small on a cold cache (measured kinds)
    code, _, err = run_cli(capsys, *args, "--out", tmp_path / "cold")
    assert code == 0, err
    assert list((tmp_path / "cache" / "records").glob("*.record"))
    with monkeypatch.context() as m:
        _no_loading(m)
        code, _, err = run_cli(capsys, *args, "--out", tmp_path / "warm")
    assert code == 0, err
    assert "warning" not in err.lower()
    cold, warm = _outputs(tmp_path / "cold"), _outputs(tmp_path / "warm")
    assert warm[0].keys() == cold[0].keys() and len(cold[0]) >= 3
    for name in cold[0]:
        assert warm[0][name] == cold[0][name], name
    assert warm[1] == cold[1]


def test_warm_path_loads_the_model_when_the_cache_lost_it(predict_setup: tuple[Path, Path], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A record without its compiled or converted models (deleted) loads the weights then and converts them
    again: same maps; a damaged record is ignored and written again; another checkpoint gets its own record."""
    ckpt, ortho = predict_setup
    cache = tmp_path / "cache"
    _, _, first = _predict(capsys, ckpt, ortho, tmp_path / "a", cache, monkeypatch)
    for entry in cache.rglob("*"):
        if entry.suffix in (".ir", ".blob"):
            entry.unlink()
    _, err, again = _predict(capsys, ckpt, ortho, tmp_path / "b", cache, monkeypatch)
    assert "warning" not in err.lower()
    np.testing.assert_array_equal(again, first)
    (record,) = list((cache / "records").glob("*.record"))
    record.write_bytes(bytes(record.stat().st_size))  # zero-filled: not a record any more
    _, err, healed = _predict(capsys, ckpt, ortho, tmp_path / "c", cache, monkeypatch)
    np.testing.assert_array_equal(healed, first)
    assert record.read_bytes() != bytes(record.stat().st_size)  # written again by the run that loaded the model
    # another checkpoint (other weights): another record, other maps
    import torch

    model, meta = tiny_d3net()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01)
    save_checkpoint(ckpt, model, meta)
    _, _, other = _predict(capsys, ckpt, ortho, tmp_path / "d", cache, monkeypatch)
    assert len(list((cache / "records").glob("*.record"))) == 2
    assert not np.array_equal(other, first)


def test_checkpoint_replaced_during_a_warm_run_stops_it(predict_setup: tuple[Path, Path], tmp_path: Path) -> None:
    """The model a record stands for is loaded only from the bytes the run started with: a file replaced in
    between is refused, with a message naming it and what to do."""
    from aerialmtl.errors import CheckpointError
    from aerialmtl.formats.checkpoint import file_sha256, read_model
    from aerialmtl.inference.model_record import CheckpointModel, make_record

    ckpt, _ = predict_setup
    model, meta, digest = read_model(ckpt)
    assert digest == file_sha256(ckpt)
    record = make_record(model, meta)
    assert record is not None and record.meta == meta and record.outputs == model.outputs
    lazy = CheckpointModel(ckpt, digest, record)
    import torch

    with torch.no_grad():
        next(model.parameters()).add_(1.0)
    save_checkpoint(ckpt, model, meta)
    with pytest.raises(CheckpointError, match="changed while this run used it.*re-run"):
        lazy.get()
