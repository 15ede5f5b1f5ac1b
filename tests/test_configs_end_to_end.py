"""Every training config shipped in configs/ runs the user's path through the CLI: tile → train (a few steps)
→ predict (default engine, T > 1) → evaluate. Plumbing only (tiny synthetic town, two steps): quality is
measured in bench/, not here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from helpers.cli import run_cli

from aerialmtl.classes import ClassScheme

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: The class scheme each config is tiled with (None: heights only). A new config fails until it is listed here.
SCHEMES = {"d3net_dfc2018": "dfc2018", "d3net_isprs": "isprs", "d3net_small_synth": "synthetic", "small_area": None}


def test_every_shipped_config_is_covered() -> None:
    assert {p.stem for p in CONFIGS.glob("*.yaml")} == set(SCHEMES)
    packaged = Path(__file__).resolve().parents[1] / "aerialmtl" / "resources" / "configs"
    for p in CONFIGS.glob("*.yaml"):  # the configs the package ships are the README's
        assert (packaged / p.name).read_text() == p.read_text(), p.name


@pytest.fixture(scope="module")
def town(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("town")
    from aerialmtl.cli import main

    try:
        main(["synth", str(root / "town"), "--size", "192", "--seed", "3", "--gsd", "0.5"])
    except SystemExit as exc:
        assert not exc.code
    return root / "town"


def _labels_in(scheme: str, town: Path, out: Path) -> Path:
    """The town's labels recoded into ``scheme``'s codes (cycled): a raster the scheme accepts."""
    codes = np.array([c.code for c in ClassScheme.load(scheme).classes])
    with rasterio.open(town / "labels.tif") as src:
        lab = src.read(1)
        profile = src.profile
    recoded = codes[lab.astype(np.int64) % len(codes)].astype(profile["dtype"])
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(recoded, 1)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_config_tile_train_predict_evaluate(name: str, town: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture) -> None:
    _user_path(CONFIGS / f"{name}.yaml", SCHEMES[name], town, tmp_path, capsys)


#: Options beside the shipped configs' values, each on the config a user would change: the height-bin head
#: and the height balance, the scale's own decoder (small-area recipe), the balance on the paper's L1 loss
#: (small synthetic D3-Net).
OPTIONS = {
    "small_area+height_bins+height_balance": ("small_area", {"model": {"height_bins": 8},
                                                             "loss": {"height_balance": 0.5}}),
    "d3net_small_synth+height_balance": ("d3net_small_synth", {"loss": {"height_balance": 0.5}}),
    "small_area+scale_decoder": ("small_area", {"model": {"scale_decoder": True}}),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(OPTIONS))
def test_options_tile_train_predict_evaluate(case: str, town: Path, tmp_path: Path,
                                             capsys: pytest.CaptureFixture) -> None:
    name, changes = OPTIONS[case]
    cfg = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
    for section, values in changes.items():
        cfg[section].update(values)
    path = tmp_path / f"{case}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    _user_path(path, SCHEMES[name], town, tmp_path, capsys)
    used = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())  # the options took effect
    assert all(used[section][k] == v for section, values in changes.items() for k, v in values.items())
    model = json.loads((tmp_path / "pred" / "prediction.json").read_text())["model"]
    assert ("height-bin spread" in model["height_uncertainty"]) == ("height_bins" in changes.get("model", {}))


def _user_path(config: Path, scheme: str | None, town: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """tile → train (2 steps) → predict (default engine, T = 2) → evaluate through the CLI, as a user types it."""
    args = ["tile", "--ortho", town / "ortho.tif", "--dsm", town / "dsm.tif", "--dtm", town / "dtm.tif",
            "--size", 64, "--stride", 64, "--split-block", 32, "--out", tmp_path / "tiles"]
    if scheme is not None:
        labels = town / "labels.tif" if scheme == "synthetic" else _labels_in(scheme, town, tmp_path / "labels.tif")
        args += ["--labels", labels, "--classes", scheme]
    code, _, err = run_cli(capsys, *args)
    assert code == 0, err
    cfg = yaml.safe_load(config.read_text())
    code, _, err = run_cli(capsys, "train", "--config", config, "--data", tmp_path / "tiles",
                           "--out", tmp_path / "run", "--max-steps", 2, "--quiet")
    assert code == 0, err
    code, _, err = run_cli(capsys, "predict", town / "ortho.tif", "--model", tmp_path / "run" / "best.pt",
                           "--out", tmp_path / "pred", "--mc", 2, "--quiet")
    assert code == 0, err
    info = json.loads((tmp_path / "pred" / "prediction.json").read_text())
    choice = info["engine_choice"]  # the default engine on a CPU: OpenVINO, or torch for a job too small to compile
    assert info["engine"] == choice["engine"]
    assert info["engine"] == "openvino" or not _openvino() or "cache cold" in choice["reason"]
    assert "height_std" in info["files"] and ("classes" in info["files"]) == (scheme is not None)
    assert info["model"]["encoder"] == cfg["model"].get("encoder", "densenet121")
    ev = ["evaluate", "--pred", tmp_path / "pred", "--height", town / "ndsm.tif", "--out", tmp_path / "ev" / "r.json"]
    if scheme is not None:
        ev += ["--labels", labels]
    code, _, err = run_cli(capsys, *ev)
    assert code == 0, err
    report = json.loads((tmp_path / "ev" / "r.json").read_text())
    assert report["height"]["n_pixels"] > 0 and report["uncertainty"]["height_std"]["strata"]["bins"]


def _openvino() -> bool:
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False
    return True
