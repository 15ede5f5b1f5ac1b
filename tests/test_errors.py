"""Error messages name parameters once: Python names from the library, the command's options from the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers.rasters import write_raster

from aerialmtl.cli import cli
from aerialmtl.cli.options import flags_for
from aerialmtl.errors import AerialMTLError, InputError, render
from aerialmtl.tiling.grid import count_windows


def test_marks_read_as_python_names_or_as_the_commands_options() -> None:
    text = "‹tile› must be a multiple of 32, got 100; pass e.g. ‹tile=512›, or ‹overwrite=True›; see `gdalinfo`"
    assert render(text) == (
        "tile must be a multiple of 32, got 100; pass e.g. tile=512, or overwrite=True; see `gdalinfo`")
    assert render(text, flags_for("predict")) == (
        "--window must be a multiple of 32, got 100; pass e.g. --window 512, or --overwrite; see `gdalinfo`")
    err = InputError(text, param="tile")
    assert str(err) == render(text) and err.param == "tile" and isinstance(err, ValueError)
    assert AerialMTLError("plain text").render(flags_for("tile")) == "plain text"
    # the same library parameter is another option in another command
    assert render("‹aoi›", flags_for("predict")) == "--aoi" and render("‹aoi›", flags_for("tile")) == "--split-aoi"


def test_library_errors_use_parameter_names() -> None:
    with pytest.raises(InputError, match=r"use stride ≤ size \(e\.g\. stride=32\)") as info:
        count_windows(100, 100, 32, 40)
    assert info.value.param == "stride"


def test_a_bad_value_checked_by_the_library_is_a_usage_error_of_its_option(tmp_path: Path) -> None:
    ortho = write_raster(tmp_path / "o.tif", np.full((3, 40, 40), 100, np.uint8))
    ndsm = write_raster(tmp_path / "n.tif", np.ones((40, 40), np.float32))
    base = ["tile", "--ortho", str(ortho), "--ndsm", str(ndsm), "--out", str(tmp_path / "t"), "--quiet"]
    res = CliRunner().invoke(cli, [*base, "--gsd", "-1"])
    assert res.exit_code == 2 and "Usage:" in res.output
    assert "Invalid value for --gsd: must be a positive pixel size in metres, got -1.0" in res.output
    res = CliRunner().invoke(cli, [*base, "--size", "32", "--stride", "40"])
    assert res.exit_code == 2 and "Invalid value for --stride" in res.output and "use --stride ≤ --size" in res.output
    res = CliRunner().invoke(cli, [*base, "--split-block", "0"])
    assert res.exit_code == 2 and "Invalid value for --split-block" in res.output
    assert not (tmp_path / "t").exists()  # refused before any output
