"""The OpenVINO engine's on-disk cache: one :class:`~aerialmtl.stores.Store` per model, under the stores' rule.

The OpenVINO engine (:mod:`aerialmtl.inference.engines`) keeps two kinds of entry per model, in one folder
per model fingerprint below the ``openvino`` store (:func:`aerialmtl.stores.store_folder`):

* ``<part>.ir`` — the converted model (OpenVINO IR: the XML graph and the weights) of ``forward``,
  ``encode`` or ``decode``;
* ``<part>.<h>x<w>.<precision>.blob`` — that part compiled for the CPU at one window shape.

Each entry is one file carrying its own checksum (:func:`aerialmtl.stores.pack`), written whole and read back
only when it is a regular file of this user whose checksum matches: a truncated, empty, zero-filled or edited
entry, a FIFO or link at an entry's name, or another user's file is rebuilt with one warning naming it. A folder
that cannot be written means predicting without caching, with one warning naming it and how to move the cache
(``AERIALMTL_OPENVINO_CACHE``), as does a temporary folder through which the converted model cannot be
serialised (:meth:`EngineCache.serialise`): the module docstring of :mod:`aerialmtl.stores` has the whole rule.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from aerialmtl.stores import OPENVINO_ENV, Store, warn_once

#: The environment variable that moves the cache (named in the warnings).
CACHE_ENV = OPENVINO_ENV


def temporary_folder_problem(exc: BaseException) -> str:
    """A warning that the temporary folder could not take a file (``exc``).

    It names the folder, ``$TMPDIR`` and its free space; it is not about the model, which converted fine.
    """
    tmp = tempfile.gettempdir()
    why = getattr(exc, "strerror", None) or " ".join(str(exc).split()) or exc.__class__.__name__
    try:
        free = f"{shutil.disk_usage(tmp).free / 2**20:.1f} MiB free"
    except OSError:
        free = "free space unknown"
    env = os.environ.get("TMPDIR")
    where = f"$TMPDIR={env}" if env else "$TMPDIR unset"
    return (f"the temporary folder '{tmp}' ({where}, {free}) could not take the converted OpenVINO model on its way "
            f"into the cache ({why}); predicting with it without caching it (every run converts it again): free "
            f"space there, or point TMPDIR at a folder with room")


class EngineCache(Store):
    """One model's cache folder (see the module docstring); ``folder=None`` caches nothing.

    Args:
        folder: the folder of this model's entries (created on first use).
    """

    def __init__(self, folder: str | Path | None) -> None:
        super().__init__(folder, what="cached OpenVINO model", env=CACHE_ENV, kind="OpenVINO")

    def read_one(self, name: str) -> np.ndarray | None:
        """The one section of entry ``name`` as a writable uint8 array over the file's bytes as read, or ``None``.

        No copy: a compiled model of ~100 MB is then imported from it with one copy less than from :meth:`read`.
        ``None`` as :meth:`read` (an unusable entry, or one of several sections, is removed with a warning).
        """
        entry = self.entry(name, sections=1)
        return None if entry is None else np.frombuffer(entry[0], np.uint8, offset=entry[2])

    def serialise(self, save: Callable[[Path], None]) -> list[bytes] | None:
        """The files ``save(xml_path)`` writes (an IR's XML and its ``.bin`` weights), or ``None``.

        Written through a private temporary folder (OpenVINO writes files). ``None`` with one warning
        (:func:`temporary_folder_problem`) when the temporary folder cannot take them: a full or read-only
        ``$TMPDIR`` only means no caching.
        """
        try:
            with tempfile.TemporaryDirectory(prefix="aerialmtl-ov-") as tmp:
                xml = Path(tmp) / "model.xml"
                save(xml)
                return [xml.read_bytes(), xml.with_suffix(".bin").read_bytes()]
        except (OSError, RuntimeError) as exc:  # OpenVINO reports a failed write as "iostream error"
            warn_once(temporary_folder_problem(exc), stacklevel=4)
            return None


__all__ = ["CACHE_ENV", "EngineCache", "temporary_folder_problem"]
