"""The OpenVINO engine's on-disk cache: entries that carry their own checksum and heal themselves.

The OpenVINO engine (:mod:`aerialmtl.inference.engines`) keeps two kinds of entry per model, in one folder
per model fingerprint (:func:`aerialmtl.inference.engines.cache_root`):

* ``<part>.ir`` — the converted model (OpenVINO IR: the XML graph and the weights) of ``forward``,
  ``encode`` or ``decode``;
* ``<part>.<h>x<w>.<precision>.blob`` — that part compiled for the CPU at one window shape.

Each entry is one file (:func:`pack`): a magic line, the SHA-256 of the payload, the payload's section
lengths and the payload. It is written through the staging convention of :mod:`aerialmtl.io.outputs`
(``.NAME.partial``, renamed into place whole), and read back only when its checksum matches: a truncated
file, a zero-filled one of the right size (what a power loss can leave) or an edited one is rebuilt,
with one warning naming it, instead of being loaded.

A cache folder that cannot be written (read-only, a full disk, a quota) never stops a prediction:
the model is converted and compiled in memory, with one warning naming the folder and how to move the
cache (``AERIALMTL_OPENVINO_CACHE``).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import struct
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from aerialmtl.io.outputs import atomic_write

#: First bytes of every entry (the format's name and version).
MAGIC = b"AERIALMTL-OV-CACHE 1\n"
#: The environment variable that moves the cache (named in the warnings).
CACHE_ENV = "AERIALMTL_OPENVINO_CACHE"

_HEADER = struct.Struct("<32sI")  # SHA-256 of the payload, number of sections
_LENGTH = struct.Struct("<Q")  # one section's length in bytes


class CorruptEntry(ValueError):
    """A cache entry whose bytes do not match its checksum (the message says how)."""


def pack(sections: Sequence[bytes]) -> bytes:
    """One cache entry holding ``sections`` (e.g. an IR's XML and weights): magic, checksum, lengths, data."""
    payload = b"".join(sections)
    lengths = b"".join(_LENGTH.pack(len(s)) for s in sections)
    return MAGIC + _HEADER.pack(hashlib.sha256(payload).digest(), len(sections)) + lengths + payload


def unpack(data: bytes) -> list[bytes]:
    """The sections of an entry written by :func:`pack`.

    Raises:
        CorruptEntry: wrong magic, truncated, or a checksum that does not match the payload.
    """
    lengths, pos = _checked(data)
    return _sections(data, lengths, pos)


def _sections(data: bytes | bytearray, lengths: list[int], pos: int) -> list[bytes]:
    """The sections of a checked entry: ``lengths`` bytes each from ``pos`` on, copied out of ``data``."""
    view, out = memoryview(data), []
    for n in lengths:
        out.append(bytes(view[pos:pos + n]))
        pos += n
    return out


def _checked(data: bytes | bytearray) -> tuple[list[int], int]:
    """The section lengths of entry ``data`` and where its payload starts, once its checksum matches.

    Raises:
        CorruptEntry: see :func:`unpack`.
    """
    view = memoryview(data)
    if bytes(view[:len(MAGIC)]) != MAGIC:
        raise CorruptEntry("it does not start like a cache entry")
    pos = len(MAGIC)
    if len(data) < pos + _HEADER.size:
        raise CorruptEntry("it is truncated")
    digest, count = _HEADER.unpack_from(data, pos)
    pos += _HEADER.size
    if len(data) < pos + count * _LENGTH.size:
        raise CorruptEntry("it is truncated")
    lengths = [_LENGTH.unpack_from(data, pos + k * _LENGTH.size)[0] for k in range(count)]
    pos += count * _LENGTH.size
    if len(data) != pos + sum(lengths):
        raise CorruptEntry(f"it holds {len(data) - pos} bytes of data, its header says {sum(lengths)}")
    if hashlib.sha256(view[pos:]).digest() != digest:
        raise CorruptEntry("its checksum does not match its content")
    return lengths, pos


class EngineCache:
    """One model's cache folder (see the module docstring); ``folder=None`` caches nothing.

    Args:
        folder: the folder of this model's entries (created on first use).
    """

    def __init__(self, folder: str | Path | None) -> None:
        self.folder: Path | None = None if folder is None else Path(folder)
        self._warned = False

    @property
    def enabled(self) -> bool:
        """Whether there is a cache folder to use."""
        return self.folder is not None

    def _disable(self, exc: OSError, doing: str) -> None:
        """Stop caching for this run, with one warning naming the folder and how to move the cache."""
        if not self._warned:
            why = exc.strerror or exc.__class__.__name__
            warnings.warn(
                f"the OpenVINO cache folder '{self.folder}' cannot be {doing} ({why}); predicting without caching "
                f"the converted model (every run converts it again): free space there, make it writable, or move "
                f"the cache with {CACHE_ENV}=/a/writable/folder", UserWarning, stacklevel=4)
            self._warned = True
        self.folder = None

    def read(self, name: str) -> list[bytes] | None:
        """The sections of entry ``name``, or ``None`` when it is missing or was corrupt (then removed, with a
        warning, so that it is rebuilt).
        """
        entry = self._entry(name)
        return None if entry is None else _sections(*entry)

    def read_one(self, name: str) -> np.ndarray | None:
        """The one section of entry ``name`` as a writable uint8 array over the file's bytes as read (no copy:
        a compiled model of ~100 MB is then imported from it with one copy less than from :meth:`read`), or
        ``None`` as :meth:`read` (a corrupt entry, or one of several sections, is removed with a warning).
        """
        entry = self._entry(name, sections=1)
        return None if entry is None else np.frombuffer(entry[0], np.uint8, offset=entry[2])

    def _entry(self, name: str, sections: int | None = None) -> tuple[bytearray, list[int], int] | None:
        """Entry ``name`` read whole into one buffer and checked: ``(bytes, section lengths, payload start)``, or
        ``None`` when it is missing, unreadable or corrupt (or has other than ``sections`` sections): those are
        removed with a warning.
        """
        if self.folder is None:
            return None
        path = self.folder / name
        try:
            with open(path, "rb", buffering=0) as f:
                size = os.fstat(f.fileno()).st_size
                data = bytearray(size)
                got = f.readinto(data)
            if got != size:  # the file changed size under us: read it as corrupt below
                del data[got:]
        except FileNotFoundError:
            return None
        except OSError as exc:
            warnings.warn(f"cached OpenVINO model '{path}' is unreadable ({exc.strerror or exc}); rebuilding it",
                          UserWarning, stacklevel=4)
            self._remove(path)
            return None
        try:
            lengths, pos = _checked(data)
            if sections is not None and len(lengths) != sections:
                raise CorruptEntry(f"it holds {len(lengths)} sections where {sections} were expected")
        except CorruptEntry as exc:
            warnings.warn(f"cached OpenVINO model '{path}' is corrupt ({exc}); rebuilding it", UserWarning,
                          stacklevel=4)
            self._remove(path)
            return None
        return data, lengths, pos

    def write(self, name: str, sections: Sequence[bytes]) -> None:
        """Store entry ``name`` (through its staging file); an unwritable folder turns caching off."""
        if self.folder is None:
            return
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            with atomic_write(self.folder / name, tag=f"partial.{os.getpid()}") as tmp:
                tmp.write_bytes(pack(sections))
        except OSError as exc:
            self._disable(exc, "written")

    def _remove(self, path: Path) -> None:
        with contextlib.suppress(OSError):
            path.unlink()


__all__ = ["CACHE_ENV", "MAGIC", "CorruptEntry", "EngineCache", "pack", "unpack"]
