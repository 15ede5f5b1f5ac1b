"""`train`'s sun: fitted on the training split of a tile folder (orthophoto and reference heights), stored with the
area's shadow classifier and footprint in the checkpoint, or stored as unclear (and predict then writes no shadow
layers) where the area shows no sun."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio

from aerialmtl.data.synth import synthesize
from aerialmtl.sun.solar_position import grid_convergence_deg
from aerialmtl.tiling.tile import TileOptions, tile_dataset
from aerialmtl.training.sun import fit_training_sun, training_area


def _tiles(tmp_path: Path, flat: bool = False) -> tuple[Path, float, float]:
    res = synthesize(tmp_path / "town", size=384, seed=11, gsd=0.5)
    ndsm = res.ndsm
    if flat:  # an overcast day: no cast shadows in the image, and nothing the heights could explain
        with rasterio.open(res.ortho) as src:
            profile, rgb = src.profile, src.read()
        overcast = np.random.default_rng(0).integers(100, 160, size=rgb.shape).astype(np.uint8)
        with rasterio.open(res.ortho, "w", **profile) as dst:
            dst.write(overcast)
    out = tmp_path / "tiles"
    tile_dataset(res.ortho, out, ndsm=ndsm, options=TileOptions(size=64, stride=64), progress=False)
    return out, res.sun_azimuth % 360.0, res.sun_elevation


def test_the_training_sun_is_the_scene_s_within_3_degrees_and_is_stored_true_north(tmp_path: Path) -> None:
    tiles, azimuth, elevation = _tiles(tmp_path)
    area = training_area(tiles)
    assert len(area.rgb) == 1 and area.rgb[0].shape[0] == 3  # the train patches pieced into one mosaic
    sun = fit_training_sun(tiles)
    assert sun.clear and sun.shadow_model is not None and "sun fitted" in sun.reason
    assert sun.grid_azimuth_deg is not None and sun.azimuth_deg is not None and sun.elevation_deg is not None
    assert abs((sun.grid_azimuth_deg - azimuth + 180.0) % 360.0 - 180.0) <= 3.0
    assert abs(sun.elevation_deg - elevation) <= 3.0
    b = sun.bounds
    assert b is not None
    convergence = grid_convergence_deg(sun.crs, (b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
    assert sun.azimuth_deg == pytest.approx((sun.grid_azimuth_deg - convergence) % 360.0, abs=1e-3)


def test_the_training_fit_keeps_squares_of_its_orthophoto_that_the_orthophoto_matches(tmp_path: Path) -> None:
    """The fit keeps chips of the training orthophoto where they lie (so predict can tell a later flight over the
    training area from this one): textured, on the tile grid, read back from the orthophoto itself at r = 1."""
    from aerialmtl.inference.sun_choice import flight_match
    from aerialmtl.sun.flight import N_CHIPS

    tiles, _, _ = _tiles(tmp_path)
    sun = fit_training_sun(tiles)
    assert sun.clear and 3 <= len(sun.chips) <= N_CHIPS
    ortho = next((tmp_path / "town").glob("*ortho*.tif"))
    with rasterio.open(ortho) as src:
        for chip in sun.chips:
            window = src.window(*chip.bounds).round_offsets().round_lengths()
            grey = src.read([1, 2, 3], window=window).astype(np.float32).mean(axis=0)
            assert np.abs(grey - chip.pixels()).max() <= 0.5  # the chip is where it says, in grey levels
    match = flight_match(ortho, sun)
    assert match.chips == len(sun.chips) and match.r == pytest.approx(1.0, abs=1e-3) and not match.other_flight


def test_the_squares_of_a_model_trained_on_chosen_bands_are_read_from_those_bands(tmp_path: Path) -> None:
    """A 4-band orthophoto with its near-infrared first (a CIR product), tiled with `--bands 2,3,4`: the squares
    are of those bands, and the orthophoto itself matches them (read from bands 1-3 it would not)."""
    from aerialmtl.inference.sun_choice import flight_match

    res = synthesize(tmp_path / "town", size=384, seed=11, gsd=0.5)
    with rasterio.open(res.ortho) as src:
        profile, rgb = src.profile, src.read()
    nir = np.random.default_rng(1).integers(0, 255, size=rgb.shape[1:], dtype=np.uint8)[None]
    profile.update(count=4, photometric="MINISBLACK")  # four data bands, none of them alpha
    cir = tmp_path / "cir.tif"
    with rasterio.open(cir, "w", **profile) as dst:
        dst.write(np.concatenate([nir, rgb]))
    tiles = tmp_path / "tiles"
    tile_dataset(cir, tiles, ndsm=res.ndsm, options=TileOptions(size=64, stride=64, bands=(2, 3, 4)), progress=False)
    sun = fit_training_sun(tiles)
    assert sun.chips and sun.chip_bands == (2, 3, 4)
    match = flight_match(cir, sun)
    assert match.r == pytest.approx(1.0, abs=1e-3) and not match.other_flight


def test_an_area_without_shadows_stores_no_sun_and_says_why(tmp_path: Path) -> None:
    tiles, _, _ = _tiles(tmp_path, flat=True)
    sun = fit_training_sun(tiles)
    assert not sun.clear and sun.azimuth_deg is None and sun.shadow_model is None
    assert sun.reason.startswith("no sun fitted")


def _dated_tiles(tmp_path: Path) -> Path:
    """The town's tile folder, its orthophoto stamped with a DateTime whose sun is far from its shadows' (so that
    the fit logs a warning)."""
    res = synthesize(tmp_path / "town", size=384, seed=11, gsd=0.5)
    with rasterio.open(res.ortho, "r+") as dst:
        dst.update_tags(TIFFTAG_DATETIME="2021:06:21 18:00:00")
    out = tmp_path / "tiles"
    tile_dataset(res.ortho, out, ndsm=res.ndsm, options=TileOptions(size=64, stride=64), progress=False)
    return out


def _train(tiles: Path, run: Path, beside: bool, monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """Two steps of a tiny D3-Net, the sun fitted beside the steps or after them; the sun of each checkpoint."""
    from aerialmtl.formats.checkpoint import load_checkpoint
    from aerialmtl.training import trainer
    from aerialmtl.training.config import TrainConfig
    from aerialmtl.training.loop import train

    monkeypatch.setattr(trainer, "beside_steps", lambda device_type: beside)
    cfg = TrainConfig.from_dict({
        "model": {"growth_rate": 4, "block_config": [1, 1, 1, 1], "num_init_features": 8, "bn_size": 2},
        "data": {"batch_size": 4, "num_workers": 0}, "schedule": {"epochs": 100}, "seed": 0, "device": "cpu",
        "calibration": {"enabled": False}, "familiarity": {"enabled": False}})
    result = train(cfg, tiles, run, max_steps=2, progress=False)
    return [load_checkpoint(p)[1].sun for p in (result.best_checkpoint, result.last_checkpoint)]


def test_the_sun_fitted_beside_the_steps_is_the_one_fitted_after_them(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch,
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    """On a GPU the sun is fitted in a process of its own while the steps run: both checkpoints store exactly the
    sun a fit after the steps stores (every field, the shadow classifier's weights included), the fit ran in that
    process (not in the trainer's), and what it logged (here: an orthophoto DateTime that disagrees with the
    shadows) is logged by the trainer."""
    import logging

    from aerialmtl.training import trainer

    tiles = _dated_tiles(tmp_path)
    after = _train(tiles, tmp_path / "after", False, monkeypatch)
    assert after[0] is not None and after[0].clear and after == [after[0], after[0]]

    def not_here(*_: object) -> None:
        raise AssertionError("fitted in the trainer's process")

    monkeypatch.setattr(trainer, "fit_training_sun", not_here)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="aerialmtl"):
        beside = _train(tiles, tmp_path / "beside", True, monkeypatch)
    assert beside == after
    said = [r for r in caplog.records if r.name == "aerialmtl.training.sun" and r.levelno == logging.WARNING]
    assert len(said) == 1 and "DateTime 2021-06-21T18:00:00Z" in said[0].getMessage()


def test_a_sun_process_that_fails_is_said_once_and_the_fit_done_after_the_steps(tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A process that cannot start, an interpreter that is not a Python (an application embedding one), or a
    process that ends without a result costs one warning naming why, never the sun."""
    from aerialmtl.training import sun_beside

    tiles, _, _ = _tiles(tmp_path)
    want = fit_training_sun(tiles)
    fails = tmp_path / "python-that-fails"
    fails.write_text("#!/bin/sh\necho 'it broke' >&2\nexit 1\n")
    fails.chmod(0o755)
    for executable, why in ((str(tmp_path / "python-missing"), "could not be started"),
                            ("/usr/bin/qgis", "not a Python interpreter"), (str(fails), "no result .it broke")):
        monkeypatch.setattr(sun_beside.sys, "executable", executable)
        with pytest.warns(RuntimeWarning, match=f"sun fit beside the training steps failed: .*{why}"):
            assert sun_beside.SunBeside(tiles).result() == want


def test_an_area_the_sun_cannot_be_fitted_on_raises_the_same_error_beside_the_steps(tmp_path: Path) -> None:
    from aerialmtl.errors import InputError
    from aerialmtl.training.sun_beside import SunBeside

    with pytest.raises(InputError) as here:
        fit_training_sun(tmp_path)
    with pytest.raises(InputError) as beside:
        SunBeside(tmp_path).result()
    assert str(beside.value) == str(here.value)


def test_a_failed_or_interrupted_run_ends_the_sun_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Training that stops with an error (here Ctrl-C during the steps) leaves no sun process running."""
    from aerialmtl.training import sun_beside, trainer

    started: list[sun_beside.SunBeside] = []

    class Spy(sun_beside.SunBeside):
        def __init__(self, data_dir: Path) -> None:
            super().__init__(data_dir)
            self.seen = self.proc
            started.append(self)

    def interrupted(*_: object) -> None:
        assert started and started[0].seen is not None and started[0].seen.poll() is None  # running beside
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer, "SunBeside", Spy)
    monkeypatch.setattr(trainer.Trainer, "run_steps", interrupted)
    tiles, _, _ = _tiles(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        _train(tiles, tmp_path / "run", True, monkeypatch)
    assert len(started) == 1 and started[0].seen is not None and started[0].seen.returncode is not None
    assert started[0].proc is None


def test_ctrl_c_while_waiting_for_the_sun_ends_its_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import subprocess

    from aerialmtl.training.sun_beside import SunBeside

    tiles, _, _ = _tiles(tmp_path)
    beside = SunBeside(tiles)
    proc = beside.proc
    assert proc is not None

    def interrupted(*_: object, **__: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(subprocess.Popen, "communicate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        beside.result()
    assert proc.returncode is not None and beside.proc is None


def test_the_sun_process_ignores_python_files_in_the_working_folder(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A user's folder holding a `json.py`, another `aerialmtl` package, and a relative tile folder: the process
    runs the trainer's own package and answers (no warning, the same sun)."""
    import warnings

    from aerialmtl.training.sun_beside import SunBeside

    tiles, _, _ = _tiles(tmp_path)
    want = fit_training_sun(tiles)
    (tmp_path / "json.py").write_text("raise SystemExit('a user script, not the json module')\n")
    (tmp_path / "aerialmtl").mkdir()
    (tmp_path / "aerialmtl" / "__init__.py").write_text("raise SystemExit('another aerialmtl')\n")
    monkeypatch.chdir(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert SunBeside(Path(tiles.name)).result() == want


def test_the_sun_process_ends_itself_once_the_trainer_is_gone() -> None:
    """Killed outright (no Ctrl-C, no cleanup), the trainer cannot end the process: it ends itself."""
    import subprocess
    import sys

    code = "from aerialmtl.training.sun_beside import _end_with; _end_with(-1)"  # -1: never its parent
    assert subprocess.run([sys.executable, "-c", code], timeout=30).returncode == 3
