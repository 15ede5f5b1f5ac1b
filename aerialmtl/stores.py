"""The stores aerialmtl keeps on disk between runs, and the one rule every one of them follows.

Every store is a folder under the package's cache folder (:func:`cache_home`), one per kind (:data:`STORES`):

* ``openvino/`` — the OpenVINO engine's converted and compiled models, one folder per model, and the records of
  the checkpoints it has seen (:mod:`aerialmtl.inference.engine_cache`, :mod:`aerialmtl.inference.model_record`;
  ``AERIALMTL_OPENVINO_CACHE`` moves this store alone);
* ``numba/`` — the machine code of the compiled kernels (:mod:`aerialmtl.jit`: the MC class kernel, the shadow
  step's kernels), which numba would otherwise keep in the installed package's ``__pycache__`` (read-only in a
  system install, and shared by every user of it).

**Where.** ``$AERIALMTL_CACHE`` when set; else the platform's user cache folder (``platformdirs``: on Linux
``$XDG_CACHE_HOME/aerialmtl`` when that is an absolute path, else ``$HOME/.cache/aerialmtl``). A ``HOME`` that is
empty, ``/`` or relative is not a home: the account's home from the password database is used instead, and where
that is no home either the stores are off for the run (one warning saying to set ``AERIALMTL_CACHE``), never a
folder at the file system's root.

**The rule** (:class:`Store`). Reading or writing an entry never crashes or hangs a run:

* an entry that is not a regular file (a FIFO, a device, a folder, a symbolic link) is never opened (a FIFO
  would block the read forever; :mod:`aerialmtl.filesafety`): it is removed where possible and rebuilt;
* an entry owned by another user is not loaded (a cache entry is code or data the run trusts): it is rebuilt;
* an empty, truncated, zero-filled or edited entry fails its checksum (:func:`pack`) and is rebuilt;
* a folder that cannot be written (read-only, full, a quota) turns the store off for the run: the run computes
  what it would have cached.

Each case gives one warning naming the path and the fix.

**A store owns only what it wrote** (:func:`owned_files`). Its entries are the files that start with
:data:`MAGIC` (every entry is written by :func:`pack`) and the files its :data:`MANIFEST` entry records beside
it (numba's machine code), at most :data:`ENTRY_DEPTH` levels below its folder. Anything else there — a user's
``mosaic.tif`` in a folder that ``AERIALMTL_OPENVINO_CACHE`` points at — is neither counted, evicted nor
cleared.

**Size.** The stores' entries together hold at most :func:`size_limit` bytes (``AERIALMTL_CACHE_LIMIT_MB``,
default :data:`DEFAULT_LIMIT_MB` MiB). After a write brings the total above it, entries are removed least
recently used first (reading an entry counts as a use: its modification time is set to now) until the total is
at most the limit, with one warning naming what went; the entry just written and files being written are kept
even where they alone exceed the limit. ``aerialmtl cache list`` shows the stores and ``aerialmtl cache clear``
empties them (:func:`list_stores`, :func:`clear_stores`), both saying how many other files they left alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
import struct
import sys
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from aerialmtl.filesafety import PARTIAL, open_regular, read_file, special_kind, write_bytes_atomic

#: Environment variable that moves every store (the package's cache folder).
ROOT_ENV = "AERIALMTL_CACHE"
#: Environment variable that moves the OpenVINO store alone (kept from earlier versions).
OPENVINO_ENV = "AERIALMTL_OPENVINO_CACHE"
#: Environment variable bounding the stores' total size, in MiB.
LIMIT_ENV = "AERIALMTL_CACHE_LIMIT_MB"
#: Default bound of the stores' total size (MiB): about ten models' OpenVINO entries at four window shapes.
DEFAULT_LIMIT_MB = 2048
#: The stores, by name (the folder under :func:`cache_home`).
STORES = ("openvino", "numba")

#: The entry recording the SHA-256 of the files a store wrote in another format beside it (numba's machine code):
#: those files are the store's too (:func:`recorded_names`).
MANIFEST = "manifest"
#: First bytes of every entry (the format's name and version).
MAGIC = b"AERIALMTL-OV-CACHE 1\n"
_HEADER = struct.Struct("<32sI")  # SHA-256 of the payload, number of sections
_LENGTH = struct.Struct("<Q")  # one section's length in bytes


class CorruptEntry(ValueError):
    """A cache entry whose bytes do not match its checksum (the message says how)."""


class NoCacheHome(OSError):
    """No folder can hold the stores (no usable ``HOME`` and no ``AERIALMTL_CACHE``)."""


# ---- where -------------------------------------------------------------------------------------------
def _is_home(path: str | None) -> bool:
    """Whether ``path`` can be a home folder: absolute and not the file system's root."""
    return bool(path) and os.path.isabs(str(path)) and Path(str(path)).resolve() != Path("/").resolve()


def _home() -> Path | None:
    """``$HOME`` when it is a home folder, else the account's home from the password database, else ``None``."""
    home = os.environ.get("HOME")
    if _is_home(home):
        return Path(str(home))
    try:
        import pwd

        entry = pwd.getpwuid(os.geteuid()).pw_dir
    except (ImportError, KeyError, OSError):
        return None
    return Path(entry) if _is_home(entry) else None


def cache_home() -> Path:
    """The package's cache folder (see the module docstring; not created here).

    Raises:
        NoCacheHome: neither ``AERIALMTL_CACHE``, an absolute ``XDG_CACHE_HOME`` nor a home folder is known.
    """
    env = os.environ.get(ROOT_ENV)
    if env:
        return Path(env).absolute()
    xdg = os.environ.get("XDG_CACHE_HOME")
    if sys.platform.startswith("linux") or not sys.platform.startswith(("win", "darwin")):
        if xdg and os.path.isabs(xdg) and _is_home(xdg):
            return Path(xdg) / "aerialmtl"
        home = _home()
        if home is None:
            raise NoCacheHome(f"HOME is {os.environ.get('HOME', '')!r}, which is no home folder; set HOME, or "
                              f"{ROOT_ENV}=/a/writable/folder to keep aerialmtl's caches there")
        return home / ".cache" / "aerialmtl"
    import platformdirs

    if not _is_home(os.environ.get("HOME")) and _home() is None and sys.platform.startswith("darwin"):
        raise NoCacheHome(f"HOME is {os.environ.get('HOME', '')!r}, which is no home folder; set HOME, or "
                          f"{ROOT_ENV}=/a/writable/folder")
    return Path(platformdirs.user_cache_dir("aerialmtl", appauthor=False))


def store_folder(name: str) -> Path:
    """The folder of store ``name`` (:data:`STORES`).

    Raises:
        NoCacheHome: see :func:`cache_home`.
    """
    if name == "openvino" and os.environ.get(OPENVINO_ENV):
        return Path(os.environ[OPENVINO_ENV]).absolute()
    if name not in STORES:
        raise ValueError(f"unknown store {name!r}; the stores are {', '.join(STORES)}")
    return cache_home() / name


_WARNED: set[str] = set()


def warn_once(message: str, stacklevel: int = 3) -> None:
    """``warnings.warn(message)`` once per process (stores are opened again and again within one run)."""
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, UserWarning, stacklevel=stacklevel)


def reset_warnings() -> None:
    """Let :func:`warn_once` warn again (called at the start of every command)."""
    _WARNED.clear()


def open_store_folder(name: str, what: str) -> Path | None:
    """:func:`store_folder`, or ``None`` with one warning when no folder can hold it (then nothing is cached)."""
    try:
        return store_folder(name)
    except NoCacheHome as exc:
        warn_once(f"{what} is not cached in this run: {exc}")
        return None


# ---- entries -----------------------------------------------------------------------------------------
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
    lengths, pos = checked(data)
    return sections_of(data, lengths, pos)


def sections_of(data: bytes | bytearray, lengths: list[int], pos: int) -> list[bytes]:
    """The sections of a checked entry: ``lengths`` bytes each from ``pos`` on, copied out of ``data``."""
    view, out = memoryview(data), []
    for n in lengths:
        out.append(bytes(view[pos:pos + n]))
        pos += n
    return out


def checked(data: bytes | bytearray) -> tuple[list[int], int]:
    """The section lengths of entry ``data`` and where its payload starts, once its checksum matches.

    Raises:
        CorruptEntry: see :func:`unpack`.
    """
    view = memoryview(data)
    if not data:
        raise CorruptEntry("it is empty")
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


def entry_problem(path: Path) -> str | None:
    """Why the file at ``path`` must not be read as an entry, as words after "is"; ``None`` when it may.

    ``None``: it is a regular file of this user, or missing. Looks at the name itself (``lstat``), never through
    a link, and opens nothing.
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    if stat.S_ISLNK(st.st_mode):
        return "a symbolic link, which aerialmtl never writes"
    if not stat.S_ISREG(st.st_mode):
        return f"{special_kind(st.st_mode)}, not a regular file"
    if hasattr(os, "geteuid") and st.st_uid != os.geteuid():
        return f"owned by another user (uid {st.st_uid}), so it is not trusted"
    if st.st_size == 0:
        return "empty"
    return None


def remove_entry(path: Path) -> None:
    """Remove entry ``path`` (a file, link, FIFO; a folder at an entry's name is left: it is never written over)."""
    with contextlib.suppress(OSError):
        path.unlink()


class Store:
    """One store's folder (see the module docstring); ``folder=None`` keeps nothing.

    Args:
        folder: the folder of the entries (created on first write).
        what: what the entries are, for messages (``"cached OpenVINO model"``).
        env: the environment variable that moves this store (named in the fixes).
        kind: the store's kind for messages (``"OpenVINO"``: "the OpenVINO cache folder ...").
    """

    def __init__(self, folder: str | Path | None, what: str = "cache entry", env: str = ROOT_ENV,
                 kind: str = "aerialmtl") -> None:
        self.folder: Path | None = None if folder is None else Path(folder)
        self.what = what
        self.env = env
        self.kind = kind

    @property
    def enabled(self) -> bool:
        """Whether there is a folder to use."""
        return self.folder is not None

    def disable(self, exc: BaseException, doing: str) -> None:
        """Stop using the folder for this run, with one warning naming it and how to move the store."""
        why = getattr(exc, "strerror", None) or " ".join(str(exc).split()) or exc.__class__.__name__
        warn_once(f"the {self.kind} cache folder '{self.folder}' cannot be {doing} ({why}); predicting without caching "
                  f"(every run computes the {self.what} again): free space there, make it writable, or move the "
                  f"cache with {self.env}=/a/writable/folder", stacklevel=4)
        self.folder = None

    def problem(self, path: Path, why: str) -> None:
        """One warning that entry ``path`` is not used (``why``), and its removal so that it is rebuilt."""
        warn_once(f"{self.what} '{path}' is {why}; rebuilding it (if this repeats, remove the file, or "
                  f"move the cache with {self.env}=/a/writable/folder)", stacklevel=5)
        remove_entry(path)

    def path(self, name: str) -> Path:
        """The path of entry ``name`` (the store must be enabled)."""
        assert self.folder is not None
        return self.folder / name

    def raw(self, name: str) -> bytearray | None:
        """The bytes of entry ``name``, or ``None`` when it is missing or must not be used.

        Checked as a file under the rule, not as an entry; one that must not be used is warned about and removed
        where possible. Marks the entry used.
        """
        if self.folder is None:
            return None
        path = self.folder / name
        why = entry_problem(path)
        if why is not None:
            self.problem(path, why)
            return None
        try:
            data = read_file(path)
        except OSError as exc:
            self.problem(path, f"unreadable ({getattr(exc, 'strerror', None) or exc})")
            return None
        if data is not None:
            with contextlib.suppress(OSError):
                os.utime(path)  # last use, for eviction
        return data

    def entry(self, name: str, sections: int | None = None) -> tuple[bytearray, list[int], int] | None:
        """Entry ``name`` read whole and checked: ``(bytes, section lengths, payload start)``, or ``None``.

        ``None`` when it is missing or unusable (see :meth:`raw`, :func:`checked`; or it has other than
        ``sections`` sections): unusable ones are removed with a warning.
        """
        data = self.raw(name)
        if data is None:
            return None
        try:
            lengths, pos = checked(data)
            if sections is not None and len(lengths) != sections:
                raise CorruptEntry(f"it holds {len(lengths)} sections where {sections} were expected")
        except CorruptEntry as exc:
            self.problem(self.path(name), f"corrupt ({exc})")
            return None
        return data, lengths, pos

    def read(self, name: str) -> list[bytes] | None:
        """The sections of entry ``name``, or ``None`` (see :meth:`entry`)."""
        entry = self.entry(name)
        return None if entry is None else sections_of(*entry)

    def write(self, name: str, sections: Sequence[bytes]) -> None:
        """Store entry ``name`` whole, then evict least recently used entries beyond :func:`size_limit`.

        Written as ``.NAME.partial.PID``, then renamed into place (:func:`aerialmtl.filesafety.write_bytes_atomic`);
        an unwritable folder turns the store off.
        """
        self.write_raw(name, pack(sections))

    def write_raw(self, name: str, data: bytes) -> None:
        """Store ``data`` as entry ``name`` as it is (see :meth:`write`)."""
        if self.folder is None:
            return
        path = self.folder / name
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(path, data, tag=f"{PARTIAL}.{os.getpid()}")
        except OSError as exc:
            self.disable(exc, "written")
            return
        evict(keep=path)


# ---- size, listing, clearing ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Entry:
    """One file of a store.

    Attributes:
        store: the store's name; path: the file; size: bytes; used: last use (seconds since the epoch).
    """

    store: str
    path: Path
    size: int
    used: float


def size_limit() -> int:
    """The bound on the stores' total size in bytes (``AERIALMTL_CACHE_LIMIT_MB``, :data:`DEFAULT_LIMIT_MB`).

    Raises:
        ValueError: the variable is not a non-negative number.
    """
    text = os.environ.get(LIMIT_ENV, "").strip()
    if not text:
        return DEFAULT_LIMIT_MB * 2**20
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not 0 <= mb < float("inf"):
        raise ValueError(f"{LIMIT_ENV}={text!r} is not a size in MiB; set it to a number ≥ 0 (e.g. 2048) or unset it")
    return int(mb * 2**20)


def store_folders() -> dict[str, Path]:
    """Each store's folder (empty when no folder can hold them: :class:`NoCacheHome`)."""
    try:
        return {name: store_folder(name) for name in STORES}
    except NoCacheHome:
        return {}


def is_entry(path: Path) -> bool:
    """Whether ``path`` is an entry a store wrote: a regular file of this user that starts with :data:`MAGIC`.

    Read without blocking, never through a link. A user's own file in a store's folder is not one.
    """
    if entry_problem(path) is not None:
        return False
    try:
        fd = open_regular(path)
    except OSError:
        return False
    with os.fdopen(fd, "rb", buffering=0) as f:
        return f.read(len(MAGIC)) == MAGIC


def recorded_names(folder: Path) -> frozenset[str]:
    """The names of the files in ``folder`` that a store wrote in another format than its entries.

    Such as numba's machine code, as the folder's :data:`MANIFEST` entry records them; empty without a valid one.
    """
    import json

    path = folder / MANIFEST
    if not is_entry(path):
        return frozenset()
    try:
        data = read_file(path)
        (section,) = unpack(bytes(data or b""))
        table = json.loads(section)
    except (OSError, ValueError):
        return frozenset()
    if not isinstance(table, dict):
        return frozenset()
    return frozenset(str(n) for n in table if isinstance(n, str) and "/" not in n and n != MANIFEST)


#: How deep below a store's folder its entries lie (``openvino/<model>/<part>.ir``, ``openvino/records/...``,
#: ``numba/<file>``): nothing deeper is looked at, so a store pointed at a project folder never walks it.
ENTRY_DEPTH = 2


def _candidates(folder: Path, depth: int = ENTRY_DEPTH) -> Iterator[Path]:
    """The files (not folders, links not followed) at most ``depth`` levels below ``folder``."""
    try:
        with os.scandir(folder) as it:
            found = list(it)
    except OSError:
        return
    for item in sorted(found, key=lambda e: e.name):
        try:
            is_dir = item.is_dir(follow_symlinks=False)
        except OSError:
            continue
        if is_dir:
            if depth > 1:
                yield from _candidates(Path(item.path), depth - 1)
        else:
            yield Path(item.path)


def owned_files(folder: Path) -> tuple[list[Path], list[Path]]:
    """``(owned, other)``: the files below store folder ``folder`` that the store wrote, and every other one.

    At most :data:`ENTRY_DEPTH` levels down. Owned: :func:`is_entry`, or a name its :data:`MANIFEST` records
    beside it. Other: a user's files, never counted, never removed.
    """
    owned: list[Path] = []
    other: list[Path] = []
    recorded: dict[Path, frozenset[str]] = {}
    for path in _candidates(folder):
        if path.parent not in recorded:
            recorded[path.parent] = recorded_names(path.parent)
        mine = is_entry(path) or (path.name in recorded[path.parent] and entry_problem(path) is None)
        (owned if mine else other).append(path)
    return owned, other


def entries(names: Sequence[str] = STORES) -> list[Entry]:
    """The entries of stores ``names`` (:func:`owned_files`), oldest use first.

    A user's files in a store's folder are not entries.
    """
    out: list[Entry] = []
    for name, folder in store_folders().items():
        if name not in names:
            continue
        for path in owned_files(folder)[0]:
            with contextlib.suppress(OSError):
                st = os.lstat(path)
                out.append(Entry(name, path, st.st_size, st.st_mtime))
    return sorted(out, key=lambda e: e.used)


def _staging(path: Path) -> bool:
    """Whether ``path`` is a store's staging file (``.NAME.partial.PID``: another process may be writing it)."""
    return path.name.startswith(".") and ".partial." in path.name


def evict(limit: int | None = None, keep: Path | None = None) -> list[Entry]:
    """Remove least recently used entries until the stores' entries hold at most ``limit`` bytes.

    ``limit`` defaults to :func:`size_limit`. ``keep`` and files being written (staging files) are never removed,
    nor is any file that is not an entry (:func:`owned_files`). Returns what was removed; the first eviction of a
    command says what it removed in one warning.
    """
    try:
        limit = size_limit() if limit is None else limit
    except ValueError as exc:
        warn_once(f"{exc}; using {DEFAULT_LIMIT_MB} MiB")
        limit = DEFAULT_LIMIT_MB * 2**20
    found = entries()
    total = sum(e.size for e in found)
    removed: list[Entry] = []
    for e in found:
        if total <= limit:
            break
        if (keep is not None and e.path == keep) or _staging(e.path):
            continue
        with contextlib.suppress(OSError):
            e.path.unlink()
            total -= e.size
            removed.append(e)
    if removed and "evicted" not in _WARNED:  # once per command: a tiny limit evicts at every write
        _WARNED.add("evicted")
        listed = ", ".join(f"'{e.path}'" for e in removed[:3]) + (", ..." if len(removed) > 3 else "")
        warn_once(f"the aerialmtl caches held more than their limit of {limit / 2**20:.1f} MiB ({LIMIT_ENV}): removed "
                  f"{len(removed)} least recently used entr{'y' if len(removed) == 1 else 'ies'} of their own "
                  f"({sum(e.size for e in removed) / 2**20:.1f} MiB: {listed}), rebuilt when needed; other files "
                  f"in their folders are never removed. Raise {LIMIT_ENV} to keep more (said once per command)",
                  stacklevel=4)
    return removed


def list_stores() -> list[tuple[str, Path, int, int, int]]:
    """``(store, folder, entries, bytes, other files)`` of each store.

    Folders that do not exist yet have 0 entries; other files are those in a store's folder that no store wrote
    (:func:`owned_files`).

    Raises:
        NoCacheHome: see :func:`cache_home`.
    """
    out = []
    for name in STORES:
        folder = store_folder(name)
        owned, other = owned_files(folder)
        size = 0
        for path in owned:
            with contextlib.suppress(OSError):
                size += os.lstat(path).st_size
        out.append((name, folder, len(owned), size, len(other)))
    return out


def clear_stores(names: Sequence[str] = STORES) -> tuple[int, int, int]:
    """Remove every entry of stores ``names`` and the folders that leaves empty: ``(files, bytes, other files left)``.

    Entries as :func:`owned_files` tells them. A user's files in a store's folder stay, and are counted as left.

    Raises:
        NoCacheHome: see :func:`cache_home`.
        OSError: an entry cannot be removed (the message names it).
    """
    folders = {name: store_folder(name) for name in names}
    files = size = left = 0
    for folder in folders.values():
        owned, other = owned_files(folder)
        left += len(other)
        for path in owned:
            st = os.lstat(path)
            path.unlink()
            files, size = files + 1, size + st.st_size
        for parent in sorted({p.parent for p in owned}, key=lambda p: len(p.parts), reverse=True):
            if parent != folder:
                with contextlib.suppress(OSError):
                    parent.rmdir()  # only when empty: a folder with a user's file stays
    return files, size, left


__all__ = ["DEFAULT_LIMIT_MB", "ENTRY_DEPTH", "LIMIT_ENV", "MAGIC", "MANIFEST", "OPENVINO_ENV", "ROOT_ENV", "STORES",
           "CorruptEntry", "Entry", "NoCacheHome", "Store", "cache_home", "checked", "clear_stores", "entries",
           "entry_problem", "evict", "is_entry", "list_stores", "open_store_folder", "owned_files", "pack",
           "recorded_names", "remove_entry", "reset_warnings", "sections_of", "size_limit", "store_folder",
           "store_folders", "unpack", "warn_once"]
