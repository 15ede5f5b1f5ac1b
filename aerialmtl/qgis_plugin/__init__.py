"""The aerialmtl QGIS plugin: a Processing provider that runs the installed ``aerialmtl`` command line.

This folder is the plugin's source: ``aerialmtl qgis-plugin aerialmtl_processing.zip`` packs it as the
plugin folder ``aerialmtl_processing/`` (QGIS: Plugins → Manage and Install Plugins → Install from ZIP).
The plugin imports nothing from aerialmtl (QGIS's Python has no torch): it runs the command line, reads
its ``--progress json`` lines, and stops it with SIGTERM on Cancel.

Modules: :mod:`.spec` (algorithms and their parameters as data, command lines), :mod:`.runner` (running a
command, progress, cancel) need no QGIS; ``provider``, ``algorithm`` and ``plugin`` are the QGIS side.
"""

from __future__ import annotations

from typing import Any


def classFactory(iface: Any) -> Any:  # the name QGIS looks for
    """QGIS's entry point: the plugin object."""
    from .plugin import AerialMTLPlugin  # imports qgis: only inside QGIS (spec/runner load without it)

    return AerialMTLPlugin(iface)
