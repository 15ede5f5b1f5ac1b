"""The QGIS plugin's zip: the plugin source (:mod:`aerialmtl.qgis_plugin`) as plugin folder ``aerialmtl_processing``.

QGIS installs it with Plugins → Manage and Install Plugins → Install from ZIP. The plugin runs the
``aerialmtl`` command line of this installation; see :mod:`aerialmtl.qgis_plugin`.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.filesafety import atomic_write

#: The plugin folder inside the zip (the name QGIS installs it under).
PLUGIN_FOLDER = "aerialmtl_processing"
#: The plugin's source folder in the installed package.
PLUGIN_SOURCE = Path(__file__).parent / "qgis_plugin"
#: The files that make the plugin (sources and QGIS's metadata).
PLUGIN_FILES = ("__init__.py", "algorithm.py", "metadata.txt", "plugin.py", "provider.py", "runner.py", "spec.py")


def build_plugin_zip(out: str | Path, overwrite: bool = False) -> Path:
    """Write the QGIS plugin zip to ``out`` (a ``.zip`` path); returns it.

    Raises:
        InputError: ``out`` does not end in ``.zip``.
        OutputExistsError: ``out`` exists and ``overwrite`` is false.
    """
    out = Path(out)
    if out.suffix.lower() != ".zip":
        raise InputError(f"‹out› must be a .zip path, got '{out}'; pass e.g. out=aerialmtl_processing.zip")
    if out.exists() and not overwrite:
        raise OutputExistsError(f"'{out}' already exists; pass ‹overwrite=True› to replace it, or another ‹out›")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as staging, zipfile.ZipFile(staging, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in PLUGIN_FILES:
            zf.write(PLUGIN_SOURCE / name, f"{PLUGIN_FOLDER}/{name}")
    return out
