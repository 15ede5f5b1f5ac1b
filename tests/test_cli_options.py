"""The CLI's shared options and its parameter → option table, derived from the commands themselves."""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest

import aerialmtl
from aerialmtl.cli import cli
from aerialmtl.cli.options import DEVICES, PRECISIONS, RASTER, command_flags, common_flags, flags_for

PACKAGE = Path(aerialmtl.__file__).parent


def _options(name: str) -> list[tuple[str, click.Option]]:
    return [(cmd, p) for cmd, c in cli.commands.items() for p in c.params
            if isinstance(p, click.Option) and name in p.opts]


def test_every_parameter_the_library_names_in_a_message_has_an_option() -> None:
    """A mark ‹name› in any library message is shown as an option of the commands (no hand-kept table)."""
    marks = {m.group(1) for path in PACKAGE.rglob("*.py") if path.name != "errors.py"
             for m in re.finditer(r"‹([A-Za-z_][A-Za-z0-9_]*)", path.read_text(encoding="utf-8"))}
    table = common_flags()
    assert marks and sorted(marks - table.keys()) == []


def test_the_table_follows_the_commands_and_their_library_names() -> None:
    assert flags_for("predict")["checkpoint"] == "--model" and flags_for("predict")["ortho"] == "ORTHOS"
    assert flags_for("tile")["block_size"] == "--split-block" and flags_for("train")["max_time_s"] == "--max-time"
    assert flags_for("export")["format"] == "--format"
    assert flags_for(None)["aoi"] == "--aoi"  # outside a command the option named after the parameter wins
    assert flags_for("nope") == common_flags()
    # every option of every command is in its table, under its own name
    for name, command in cli.commands.items():
        table = command_flags(command)
        for p in command.params:
            if isinstance(p, click.Option) and p.name != "help":
                assert table[p.name] in p.opts, (name, p.name)


@pytest.mark.parametrize("flag", ["--overwrite", "--quiet", "--device", "--precision", "--compile"])
def test_shared_options_read_the_same_in_every_command(flag: str) -> None:
    found = _options(flag)
    assert len(found) >= 2, f"{flag} is shared"
    for _, p in found:
        assert p.is_flag == found[0][1].is_flag
        if isinstance(p.type, click.Choice):
            assert tuple(p.type.choices) in (DEVICES, PRECISIONS)
    if flag == "--quiet":
        assert {p.help for _, p in found} == {"No progress bar."}


def test_every_raster_input_takes_gdal_paths() -> None:
    """Options that read rasters take URLs and /vsi paths (as strings, never pathlib.Path)."""
    rasters = {("predict", "orthos"), ("tile", "ortho"), ("tile", "dsm"), ("tile", "dtm"), ("tile", "ndsm"),
               ("tile", "labels"), ("evaluate", "height_ref"), ("evaluate", "dsm_ref"), ("evaluate", "dtm_ref"),
               ("evaluate", "labels_ref"), ("buildings", "dtm")}
    for command, name in rasters:
        (param,) = [p for p in cli.commands[command].params if p.name == name]
        assert param.type is RASTER, (command, name)
    assert RASTER.convert("s3://bucket/a/o.tif", None, None) == "/vsis3/bucket/a/o.tif"
    with pytest.raises(click.BadParameter, match="does not exist"):
        RASTER.convert("no/such/file.tif", None, None)
