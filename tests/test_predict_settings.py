"""Predict's settings are one list, the fields of ``PredictSettings``: the command line has one option per field with
the field's default, ``prediction.json`` (``settings``, ``provenance.settings``) and the STAC item record every field
by looping over them, and the Python keywords are the field names. Adding a setting is its field, its CLI option and
its QGIS parameter (tests/test_qgis_plugin.py) and nothing else."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import click
import numpy as np
import pytest
import torch
from helpers.models import tiny_d3net
from helpers.rasters import write_raster

from aerialmtl import runtime
from aerialmtl.cli.predict import predict
from aerialmtl.errors import InputError
from aerialmtl.inference.predict import PredictSettings, predict_raster
from aerialmtl.inference.settings import ResolvedSettings

FIELDS = [f.name for f in dataclasses.fields(PredictSettings)]


def _options() -> dict[str, click.Option]:
    """Setting → the predict option that stands for it (its own name or a ``library=`` name)."""
    return {n: p for p in predict.params if isinstance(p, click.Option) and p.name
            for n in (p.name, *getattr(p, "library", ()))}


def test_every_setting_has_its_option_with_the_same_default() -> None:
    options = _options()
    missing = [f for f in FIELDS if f not in options]
    assert not missing, f"settings without a predict option: {missing}"
    ctx = click.Context(predict)
    for f in dataclasses.fields(PredictSettings):
        default = options[f.name].get_default(ctx)
        if options[f.name].is_flag and default is None:
            default = False
        if f.name == "threads":  # None and "auto" are one value (runtime.resolve_threads)
            assert f.default == default == "auto"
        assert default == f.default, f"--{f.name.replace('_', '-')}: CLI default {default!r} != {f.default!r}"


def test_every_setting_is_recorded(tmp_path: Path) -> None:
    model, meta = tiny_d3net()
    ortho = write_raster(tmp_path / "o.tif",
                         np.random.default_rng(0).integers(1, 256, size=(3, 48, 40)).astype(np.uint8))
    predict_raster(ortho, (model, meta), tmp_path / "p", mc=2, window=32, overlap=0, engine="torch", device="cpu",
                   progress=False, seed=4, tta=True)
    info = json.loads((tmp_path / "p" / "prediction.json").read_text())
    assert list(info["settings"]) == FIELDS
    assert info["settings"]["mc"] == info["mc_samples"] == 2 and info["settings"]["seed"] == 4
    assert info["settings"]["engine"] == "torch" and info["settings"]["device"] == "cpu"
    assert info["settings"]["batch_size"] == info["batch_size"] >= 1  # "auto" resolved
    assert info["settings"]["threads"]["threads"] >= 1  # resolved on the CPU
    # the shadow settings count only when the shadow features ran (this model has no shadow classifier)
    maps = {f.name for f in dataclasses.fields(PredictSettings) if f.metadata.get("maps", True) is True} - {"mc"}
    assert maps | {"mc_samples", "input_rescale"} == set(info["provenance"]["settings"])
    item = json.loads((tmp_path / "p" / "item.json").read_text())
    assert item["properties"]["aerialmtl:settings"] == info["settings"]


def test_a_new_setting_is_recorded_without_another_edit() -> None:
    """A field added to the settings (here in a subclass) is in both records with no other edit."""
    sunny = dataclasses.make_dataclass("Sunny", [("sun", str, dataclasses.field(default="auto"))],
                                       bases=(PredictSettings,), frozen=True)
    settings = sunny(mc=3)
    resolved = ResolvedSettings(torch.device("cpu"), "torch", "fp32", runtime.resolve_threads(1), 3)
    assert settings.record(resolved, 1)["sun"] == "auto"
    assert settings.provenance(resolved)["sun"] == "auto"
    assert settings.with_options(sun="none").sun == "none"


def test_keywords_are_the_field_names() -> None:
    assert PredictSettings().with_options(mc=4, seed=2) == PredictSettings(mc=4, seed=2)
    with pytest.raises(InputError, match=r"no setting progres; the settings are mc, window"):
        PredictSettings().with_options(progres=False)
    with pytest.warns(FutureWarning, match="‹tile› is deprecated"):
        assert PredictSettings().with_options(tile=512).window == 512
