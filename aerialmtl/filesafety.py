"""Opening and replacing files that someone else may have put in place, without hanging or writing through links.

The package's ground floor for files (it imports nothing of aerialmtl): the stores (:mod:`aerialmtl.stores`),
the output folders (:mod:`aerialmtl.io.outputs`) and the readers of users' files (an orthophoto's fingerprint,
a checkpoint, the layers a ``prediction.json`` lists) all open and write through it, so one rule holds for all:

* **Opening** (:func:`open_regular`, :func:`read_file`). A file is opened read-only, never blocking and, unless
  asked, never through a symbolic link: a FIFO, a device or a socket at its name would block the open or every
  read (a run that hangs without a word). What is there instead is named in the error (:func:`special_kind`).
* **Looking** (:func:`special_file`). What stands at a name that is neither a regular file nor a link, without
  opening it (``lstat``).
* **Replacing** (:func:`atomic_write`). A file is written under a hidden staging name beside its final path,
  ``.NAME.<tag>`` (:func:`staging_path`), and renamed into place when it is whole. A rename inside one folder is
  atomic, so the final path holds either the old file or the new one, never half of one; it also replaces a
  symbolic link at the final name instead of writing through it. :func:`write_bytes_atomic` writes bytes so,
  opening the staging file without following a link.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
from collections.abc import Iterator
from pathlib import Path

#: Tag of the staging file of a final file: ``.NAME.partial``.
PARTIAL = "partial"
#: Flags of every read-only open: never through a symbolic link, never blocking on a FIFO, never inherited by an
#: exec'd program.
OPEN_FLAGS = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)


# ---- what is there -------------------------------------------------------------------------------------
def special_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` that is not a regular file is, in words (``"a FIFO"``, ...)."""
    return "a FIFO" if stat.S_ISFIFO(mode) else "a folder" if stat.S_ISDIR(mode) else \
        "a socket" if stat.S_ISSOCK(mode) else "a symbolic link" if stat.S_ISLNK(mode) else \
        "a device or other special file"


def special_file(path: str | Path) -> str | None:
    """What stands at ``path`` (:func:`special_kind`) when it exists and is neither a regular file nor a link.

    ``None`` otherwise (missing, unreadable, a regular file, a symbolic link). Looks at the name itself
    (``lstat``) and opens nothing.
    """
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode) or stat.S_ISLNK(mode):
        return None
    return special_kind(mode)


# ---- opening -------------------------------------------------------------------------------------------
def open_regular(path: str | Path, follow_links: bool = False) -> int:
    """A read-only descriptor of regular file ``path``, opened without blocking and not through a link.

    Without blocking: a FIFO, a device or a socket at its name would block the open or every read. Through a
    symbolic link only with ``follow_links``. The one way aerialmtl opens a file that someone else may have put
    in place: store entries, an input's sidecars, the layers a ``prediction.json`` lists.

    Raises:
        FileNotFoundError: it is missing.
        OSError: it cannot be opened, or it is not a regular file (the message names it and what it is).
    """
    flags = OPEN_FLAGS if not follow_links else OPEN_FLAGS & ~getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise
    except OSError as exc:  # a socket (ENXIO), a link under O_NOFOLLOW (ELOOP): say what is there
        with contextlib.suppress(OSError):
            mode = (os.stat if follow_links else os.lstat)(path).st_mode
            if not stat.S_ISREG(mode):
                raise OSError(errno.EINVAL, f"'{path}' is {special_kind(mode)}, not a regular file") from exc
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, f"'{path}' is {special_kind(st.st_mode)}, not a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)  # a regular file: reads never block on it, and buffered reads want this
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_file(path: str | Path) -> bytearray | None:
    """The bytes of regular file ``path``, or ``None`` when it is missing.

    Read through :func:`open_regular`: not through a link, not blocking on a FIFO. A file that shrinks while it
    is read gives the bytes read (a checksum over them says so).

    Raises:
        OSError: it cannot be read, or it is not a regular file after all (replaced between look and open).
    """
    try:
        fd = open_regular(path)
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb", buffering=0) as f:
        size = os.fstat(fd).st_size
        data = bytearray(size)
        got = f.readinto(data)
    if got is not None and got != size:
        del data[got:]
    return data


# ---- replacing -----------------------------------------------------------------------------------------
def staging_path(final: str | Path, tag: str = PARTIAL, keep_suffix: bool = False) -> Path:
    """The hidden staging file of ``final``: ``.NAME.<tag>`` in the same folder (so a rename is atomic).

    ``keep_suffix`` appends the final suffix again (``.b.gpkg.partial.gpkg``) for writers that choose the
    format, or check it, by the file name's suffix.
    """
    final = Path(final)
    return final.with_name(f".{final.name}.{tag}" + (final.suffix if keep_suffix else ""))


@contextlib.contextmanager
def atomic_write(final: str | Path, tag: str = PARTIAL, keep_suffix: bool = False) -> Iterator[Path]:
    """Yield the staging path of ``final`` (:func:`staging_path`); rename it to ``final`` when the block ends.

    A file left at the staging name (by a killed run) is removed first. On an error (or Ctrl-C, SIGTERM) the
    staging file is removed and ``final`` is left as it was.
    """
    final = Path(final)
    tmp = staging_path(final, tag, keep_suffix)
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_bytes_atomic(final: str | Path, data: bytes, tag: str = PARTIAL) -> Path:
    """Write ``data`` to ``final`` through its staging file (:func:`atomic_write`); returns ``final``.

    The staging file is created anew, ``0o644`` (less the umask): whatever stood at its name (a killed run's half
    file, a symbolic link, a FIFO) is removed first and never written through, and one that appears again
    before the write is an error, not a hang.

    Raises:
        OSError: it cannot be written (the staging file is removed, ``final`` left as it was).
    """
    with atomic_write(final, tag) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
                     | getattr(os, "O_CLOEXEC", 0), 0o644)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
    return Path(final)


__all__ = ["OPEN_FLAGS", "PARTIAL", "atomic_write", "open_regular", "read_file", "special_file", "special_kind",
           "staging_path", "write_bytes_atomic"]
