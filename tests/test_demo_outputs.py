"""``aerialmtl demo`` names every file it writes in its "Outputs" list: the maps of the prediction folder (the
shadow layers included), its records, evaluate's plots and the demo's own record, ``demo.json``."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cli import run_cli


@pytest.mark.slow
def test_the_demo_names_every_file_it_writes(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A tiny demo (small towns, 5 steps; ~20 s on 2 cores): every file at the top of its folder, in its
    prediction folder (a ``.qml`` style stands beside its ``.tif``) and in ``previews/`` is in the list."""
    out_dir = tmp_path / "demo_out"
    code, out, err = run_cli(capsys, "demo", out_dir, "--train-size", 256, "--test-size", 256, "--train-steps", 5,
                             "--mc", 2)
    assert code == 0, err
    listing = out.split("Outputs:", 1)[1]
    written = [p for p in out_dir.iterdir() if p.is_file()]
    written += [p for p in (out_dir / "prediction").iterdir() if p.suffix != ".qml"]
    written += list((out_dir / "previews").iterdir())
    assert {p.name for p in written} >= {"demo.json", "report.json", "report.md", "height.tif", "item.json"}
    missing = sorted(p.name for p in written if p.name not in listing)
    assert not missing, f"written but not named in the Outputs list: {missing}\n{listing}"
    assert "each with its QGIS style, .qml" in listing


@pytest.mark.slow
def test_the_demo_gives_the_test_town_its_own_sun(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The demo's two towns lie at one place under different suns (two flights of one town): the test town's
    shadow layers use its own sun, given as a flight record gives it, never the training town's, and the demo
    prints no warning that its shadow features are off."""
    import json

    import rasterio

    out_dir = tmp_path / "demo_out"
    code, _, err = run_cli(capsys, "demo", out_dir, "--train-size", 256, "--test-size", 256, "--train-steps", 5,
                           "--mc", 2)
    assert code == 0, err
    assert "no shadow features" not in err, err
    sun = json.loads((out_dir / "prediction" / "prediction.json").read_text())["sun"]
    with rasterio.open(out_dir / "data" / "test_town" / "ortho.tif") as src:
        tags = src.tags()
    assert sun["source"] == "--sun", sun
    assert sun["grid_azimuth_deg"] == pytest.approx(float(tags["AERIALMTL_SUN_AZIMUTH"]) % 360.0, abs=0.01)
    assert sun["elevation_deg"] == pytest.approx(float(tags["AERIALMTL_SUN_ELEVATION"]), abs=0.01)
