"""Hostile inputs, part 4 (issue 49): files that would block a read (FIFOs where a world file or a checksummed
layer is looked for), absurd thread counts, YAML and pickle bombs, damaged feature densities and weights of the
wrong type. Each ends in seconds — a one-line error naming the file or option and the fix, or a documented
fallback — never a hang, never garbage in a folder called complete.

The cases that could hang run ``python -m aerialmtl`` in a subprocess with a timeout: a regression fails on
``subprocess.TimeoutExpired`` instead of hanging the suite.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.procs import aerialmtl, env, one_line
from helpers.rasters import write_raster

from aerialmtl.formats.checkpoint import save_checkpoint

BAD = ("Error: unexpected", "Aborted", "Traceback")
#: Seconds a subprocess may take before the case counts as a hang (python, torch and GDAL start in ~10-30 s on a
#: busy 2-core machine; the hangs this guards against never end).
HANG = 240
PREDICT = ("--mc", "1", "--window", "32", "--overlap", "8", "--engine", "torch", "--quiet")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny checkpoint and a 56×40 orthophoto."""
    root = tmp_path_factory.mktemp("hostile4")
    model, meta = tiny_d3net()
    save_checkpoint(root / "m.pt", model, meta)
    rng = np.random.default_rng(49)
    return root / "m.pt", write_raster(root / "o.tif", rng.integers(1, 256, size=(3, 40, 56)).astype(np.uint8))


def _error_line(done) -> str:
    """The one ``Error:`` line of a failed subprocess run (asserted: exit 1, nothing else on stderr)."""
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1 and len(lines) == 1 and lines[0].startswith("Error: "), done.stderr
    assert not any(b in lines[0] for b in BAD)
    return lines[0]


# ---- FIFOs where a file is read ----------------------------------------------------------------------------------
VRT = """<VRTDataset rasterXSize="56" rasterYSize="40"><SRS>EPSG:32631</SRS>
<GeoTransform>500000, 0.5, 0, 5000000, 0, -0.5</GeoTransform>{bands}</VRTDataset>"""
VRT_BAND = """<VRTRasterBand dataType="Byte" band="{b}"><SimpleSource>
<SourceFilename relativeToVRT="1">src.tif</SourceFilename><SourceBand>{b}</SourceBand></SimpleSource></VRTRasterBand>"""


@pytest.mark.parametrize("sidecar", ["o.tfw", "o.tif.aux.xml", "o.tif", "o.vrt", "src.tif"])
def test_a_fifo_world_file_or_sidecar_is_refused_not_waited_on(sidecar: str, inputs, tmp_path: Path) -> None:
    """A FIFO where GDAL reads: the world file, the PAM sidecar, the raster itself, a VRT, the file a VRT lists."""
    ckpt, ortho = inputs
    name = "o.vrt" if sidecar in ("o.vrt", "src.tif") else "o.tif"
    shutil.copy(ortho, tmp_path / "o.tif")
    (tmp_path / "o.vrt").write_text(VRT.format(bands="".join(VRT_BAND.format(b=b) for b in (1, 2, 3))))
    if sidecar in ("o.tif", "o.vrt"):
        (tmp_path / sidecar).unlink()
    os.mkfifo(tmp_path / sidecar)
    done = aerialmtl("predict", tmp_path / name, "--model", ckpt, "--out", tmp_path / "p", *PREDICT,
                     environ=env(), timeout=HANG)  # a FIFO read would block: the timeout says "hang"
    line = _error_line(done)
    assert f"'{tmp_path / sidecar}'" in line and "is a FIFO, not a regular file" in line and "remove" in line, line
    assert not (tmp_path / "p" / "prediction.json").exists()


def test_skip_existing_never_waits_on_a_fifo_its_prediction_json_names(inputs, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture) -> None:
    """A FIFO named by prediction.json's checksums, or at a layer's name, makes the folder incomplete (said on one
    line) and the run recomputes it; it is never opened."""
    ckpt, ortho = inputs
    out = tmp_path / "p"
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", out, *PREDICT)
    assert code == 0, err
    with rasterio.open(out / "height.tif") as src:
        reference = src.read(1)
    info = json.loads((out / "prediction.json").read_text())
    info["file_sha256"]["notes.fifo"] = "0" * 64  # a checksum of a file that is none of its layers
    (out / "prediction.json").write_text(json.dumps(info))
    os.mkfifo(out / "notes.fifo")
    done = aerialmtl("predict", ortho, "--model", ckpt, "--out", out, "--skip-existing", *PREDICT[:-1],
                     environ=env(), timeout=HANG)
    assert done.returncode == 0, done.stderr
    assert "recomputed" in done.stdout + done.stderr and "notes.fifo" in one_line(done.stdout + done.stderr)
    (out / "height.tif").unlink()
    os.mkfifo(out / "height.tif")  # a layer's own name
    done = aerialmtl("predict", ortho, "--model", ckpt, "--out", out, "--skip-existing", *PREDICT[:-1],
                     environ=env(), timeout=HANG)
    assert done.returncode == 0, done.stderr
    said = one_line(done.stdout + done.stderr)
    assert "recomputed" in said and "height.tif is a FIFO, not a regular file" in said, said
    with rasterio.open(out / "height.tif") as src:
        np.testing.assert_allclose(src.read(1), reference, rtol=0, atol=1e-5)  # same model, same input: same map


def test_content_checksums_refuse_a_fifo_at_once(tmp_path: Path) -> None:
    from aerialmtl.formats.checkpoint import file_sha256
    from aerialmtl.io.fingerprint import content_sha256

    os.mkfifo(tmp_path / "f")
    started = time.monotonic()
    for digest in (content_sha256, file_sha256):
        with pytest.raises(OSError, match="is a FIFO, not a regular file"):
            digest(tmp_path / "f")
    assert time.monotonic() - started < 5


# ---- threads ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["option", "env"])
def test_absurd_thread_counts_are_the_cpu_count_with_one_warning(how: str, inputs, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    from aerialmtl import runtime

    ckpt, ortho = inputs
    extra: tuple[str, ...] = ("--threads", "1000000") if how == "option" else ()
    if how == "env":
        monkeypatch.setenv(runtime.THREADS_ENV, "1000000")
    threads = torch.get_num_threads()
    try:
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", *PREDICT, *extra)
    finally:
        torch.set_num_threads(threads)
    assert code == 0, err
    cpus = runtime.usable_cpus()
    named = "--threads 1000000" if how == "option" else f"{runtime.THREADS_ENV}=1000000"
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines == [f"warning: {named} is more than the {cpus} CPU(s) this process may use; using {cpus} "
                     "thread(s)"], err
    info = json.loads((tmp_path / "p" / "prediction.json").read_text())
    assert info["threads"]["threads"] == cpus


# ---- bombs ------------------------------------------------------------------------------------------------------
def _yaml_bomb(path: Path, self_reference: bool = False) -> Path:
    """A YAML file of a few hundred bytes that stands for 10⁹ values through aliases of aliases (or refers to
    itself)."""
    if self_reference:
        path.write_text("model: &a\n  growth_rate: 4\n  more: *a\n")
        return path
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 10)]
    lines.append("model: {growth_rate: *a9}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("self_reference", [False, True])
def test_a_yaml_alias_bomb_is_refused_before_it_is_built(self_reference: bool, inputs, tmp_path: Path) -> None:
    from aerialmtl.config import MAX_YAML_VALUES

    config = _yaml_bomb(tmp_path / "train.yaml", self_reference)
    assert config.stat().st_size < 2048
    started = time.monotonic()
    done = aerialmtl("train", "--data", tmp_path / "no-tiles", "--config", config, "--out", tmp_path / "run",
                     environ=env(), timeout=HANG)
    line = _error_line(done)
    assert f"config file '{config}' expands to more than {MAX_YAML_VALUES:,} values" in line, line
    assert "write the values out" in line
    assert time.monotonic() - started < HANG
    assert not (tmp_path / "run").exists()


def test_yaml_aliases_a_config_uses_are_read() -> None:
    """Aliases stay usable: a block written once and used a few times is a normal configuration."""
    import tempfile

    from aerialmtl.config import read_yaml

    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as fh:
        fh.write("base: &b {lr: 1.0e-4, betas: [0.9, 0.99]}\nfirst: *b\nsecond: *b\n")
    try:
        data = read_yaml(fh.name)
    finally:
        os.unlink(fh.name)
    assert data["first"] == data["second"] == {"lr": 1e-4, "betas": [0.9, 0.99]}


def _pickle_bomb(path: Path, cycle: bool = False) -> Path:
    """A checkpoint of a few KB whose metadata is 10²⁴ values through shared lists (or a list holding itself)."""
    import torch

    if cycle:
        bomb: list = []
        bomb.append(bomb)
    else:
        bomb = list(range(100))
        for _ in range(11):
            bomb = [bomb] * 100
    torch.save({"format": "aerialmtl-checkpoint", "format_version": 1, "meta": {"model": bomb}, "state_dict": {}},
               path)
    return path


@pytest.mark.parametrize("cycle", [False, True])
def test_a_pickle_bomb_checkpoint_is_refused_at_once(cycle: bool, inputs, tmp_path: Path) -> None:
    from aerialmtl.formats.checkpoint import MAX_CHECKPOINT_VALUES

    _, ortho = inputs
    ckpt = _pickle_bomb(tmp_path / "bomb.pt", cycle)
    assert ckpt.stat().st_size < 64 * 1024
    done = aerialmtl("predict", ortho, "--model", ckpt, "--out", tmp_path / "p", *PREDICT, environ=env(),
                     timeout=HANG)
    line = _error_line(done)
    assert f"checkpoint '{ckpt}' holds more than {MAX_CHECKPOINT_VALUES:,} values" in line, line
    assert "use a checkpoint written by `aerialmtl train`" in line
    assert not (tmp_path / "p").exists()


def test_counting_a_payload_is_fast_and_exact() -> None:
    from aerialmtl.formats.checkpoint import expanded_values

    shared = [1, 2]
    assert expanded_values([shared, shared, (shared,)]) == 11  # the outer list, twice 3, the tuple's 1 + 3
    assert expanded_values({"x": [shared, shared]}) == 1 + 1 + 7
    bomb: list = [0]
    for _ in range(60):
        bomb = [bomb, bomb]
    started = time.monotonic()
    assert expanded_values(bomb, limit=1000) == 1001
    assert time.monotonic() - started < 1.0


# ---- the feature density and the weights of a checkpoint ---------------------------------------------------------
@pytest.fixture(scope="module")
def with_density(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny checkpoint with a density fitted on 6-channel features of encoder level 1 (stride 4)."""
    import dataclasses

    from aerialmtl.models.familiarity import fit_density

    model, meta = tiny_d3net()
    dens = fit_density(np.random.default_rng(5).normal(size=(400, 6)), (1,), 4, dims=3, components=2)
    path = tmp_path_factory.mktemp("density") / "m.pt"
    save_checkpoint(path, model, dataclasses.replace(meta, familiarity=dens))
    return path


def _edited(src: Path, dst: Path, edit) -> Path:
    """A copy of checkpoint ``src`` with its payload changed by ``edit`` (what a damaged or hand-edited file is)."""
    import torch

    payload = torch.load(src, weights_only=True)
    edit(payload)
    torch.save(payload, dst)
    return dst


def _density(**changes: object):
    def edit(payload: dict) -> None:
        payload["meta"]["familiarity"].update(changes)
    return edit


DAMAGED_DENSITIES = {
    "a level the model lacks": (_density(levels=[7]), "encoder levels [7]"),
    "a repeated level": (_density(levels=[1, 1]), "encoder levels [1, 1]"),
    "another level's width": (_density(levels=[2]), "reads 6 channels at encoder levels [2], where the model has 5"),
    "zero weights": (_density(weights=[0.0, 0.0]), "mixture weights [0, 0], which must be > 0 and sum to 1"),
    "negative weights": (_density(weights=[1.5, -0.5]), "mixture weights [1.5, -0.5]"),
    "weights not summing to 1": (_density(weights=[0.2, 0.2]), "mixture weights [0.2, 0.2]"),
    "constant quantiles": (_density(quantiles=[3.0] * 201), "a quantile table without spread"),
    "a zero basis": (_density(basis=[[0.0] * 6] * 3), "a basis whose rows are not orthonormal"),
    "a negative precision diagonal": (
        lambda p: p["meta"]["familiarity"]["precision_chol"].__setitem__(
            0, [-v for v in p["meta"]["familiarity"]["precision_chol"][0]]),
        "precision factors that are not lower triangular with a positive diagonal"),
    "values beyond float32": (_density(centre=[1e300] * 6), "values beyond float32"),
    "a NaN": (_density(centre=[float("nan")] * 6), "familiarity.centre[0]: expected a finite number, got nan"),
}


@pytest.mark.parametrize("case", list(DAMAGED_DENSITIES))
def test_a_damaged_feature_density_is_refused_before_any_map(case: str, with_density: Path, inputs, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    """Refused, not a NaN or constant unfamiliarity layer in a folder called complete (decided: the density is
    part of what the checkpoint says; a damaged one means an edited or damaged file, as damaged weights do)."""
    edit, needle = DAMAGED_DENSITIES[case]
    ckpt = _edited(with_density, tmp_path / "bad.pt", edit)
    code, _, err = run_cli(capsys, "predict", inputs[1], "--model", ckpt, "--out", tmp_path / "p", *PREDICT)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1 and lines[0].startswith("Error: "), err
    assert f"checkpoint '{ckpt}'" in lines[0] and needle in lines[0], lines[0]
    assert "use the checkpoint as `train` wrote it" in lines[0] or "use a checkpoint written by" in lines[0], lines[0]
    assert not (tmp_path / "p").exists()


def test_a_sound_density_still_writes_a_finite_varied_layer(with_density: Path, inputs, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    code, _, err = run_cli(capsys, "predict", inputs[1], "--model", with_density, "--out", tmp_path / "p", *PREDICT)
    assert code == 0, err
    with rasterio.open(tmp_path / "p" / "unfamiliarity.tif") as src:
        u = src.read(1)
    assert np.isfinite(u).all() and 0 <= u.min() < u.max() <= 1


@pytest.mark.parametrize("dtype", ["int8", "bool", "float16"])
def test_float_weights_of_another_kind_are_refused_naming_the_tensor(dtype: str, inputs, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    import torch

    key = "encoder.features.conv0.weight"

    def edit(payload: dict) -> None:
        payload["state_dict"][key] = payload["state_dict"][key].to(getattr(torch, dtype))

    ckpt = _edited(inputs[0], tmp_path / f"{dtype}.pt", edit)
    code, _, err = run_cli(capsys, "predict", inputs[1], "--model", ckpt, "--out", tmp_path / "p", *PREDICT)
    if dtype == "float16":  # a float of another width (a start stored as float16) is cast, not refused
        assert code == 0, err
        return
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1, err
    assert f"checkpoint '{ckpt}': tensor '{key}' is stored as {dtype}, where the model's is float32" in lines[0]
    assert not (tmp_path / "p").exists()


# ---- what held keeps holding ------------------------------------------------------------------------------------
def test_skip_existing_recomputes_when_a_mask_sidecar_appears(inputs, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture) -> None:
    """A regular sidecar is still read and fingerprinted (only FIFOs, sockets and devices are refused): an external
    mask that appears after a run makes --skip-existing recompute."""
    ckpt, ortho = inputs
    shutil.copy(ortho, tmp_path / "o.tif")
    args = ("predict", tmp_path / "o.tif", "--model", ckpt, "--out", tmp_path / "p", "--skip-existing", *PREDICT[:-1])
    code, out, err = run_cli(capsys, *args)
    assert code == 0, err
    code, out, err = run_cli(capsys, *args)
    assert code == 0 and "skipped" in out + err, out + err
    with rasterio.open(tmp_path / "o.tif") as src:
        profile = {**src.profile, "count": 1, "dtype": "uint8", "nodata": None}
    mask = np.full((40, 56), 255, np.uint8)
    mask[:, :20] = 0  # the left 20 columns masked out
    with rasterio.open(tmp_path / "o.tif.msk", "w", **profile) as dst:
        dst.write(mask, 1)
    code, out, err = run_cli(capsys, *args)
    said = one_line(out + err)
    assert code == 0 and "recomputed" in said and "o.tif.msk appeared" in said, said
    code, out, err = run_cli(capsys, *args)
    assert code == 0 and "skipped" in out + err, out + err  # and the new state is complete in turn
