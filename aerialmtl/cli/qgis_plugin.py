"""`aerialmtl qgis-plugin`: the QGIS Processing plugin as a zip to install in QGIS; a thin command over
:func:`aerialmtl.plugin_zip.build_plugin_zip`.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import click

from aerialmtl.cli.options import argument, overwrite_option


@click.command(name="qgis-plugin")
@argument("out", type=click.Path(dir_okay=False, path_type=Path), default=Path("aerialmtl_processing.zip"),
          required=False)
@overwrite_option(help="Replace an existing zip.")
def qgis_plugin(out: Path, overwrite: bool) -> None:
    """Write the QGIS plugin to OUT [default: aerialmtl_processing.zip].

    \b
    In QGIS (3.22 or later): Plugins → Manage and Install Plugins → Install from ZIP → OUT.
    The aerialmtl algorithms (predict, buildings, evaluate, tile, train, export) then appear in the
    Processing toolbox and run this installation's `aerialmtl` program; if QGIS does not find it on its
    PATH, set it in Settings → Options → Processing → Providers → aerialmtl.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.plugin_zip import build_plugin_zip

    path = build_plugin_zip(out, overwrite=overwrite)
    program = shutil.which("aerialmtl")
    click.echo(f"QGIS plugin written to {path}; install it in QGIS with Plugins → Manage and Install Plugins → "
               "Install from ZIP")
    if program:
        click.echo(f"the plugin runs `aerialmtl`; this installation's program is {program}")
