"""Output folders: one staging convention, one overwrite policy, one writer at a time.

Every command writes through this module (:class:`OutputFolder`), so the rules are the same everywhere:

* **Staging.** A file is written under a hidden name beside its final path, ``.NAME.partial``
  (:func:`aerialmtl.filesafety.staging_path`; other stages of the same file use other tags,
  ``.NAME.staging``), and renamed into place when it is whole (:func:`aerialmtl.filesafety.atomic_write`,
  the package's one atomic write; :func:`write_text_atomic`). A rename inside one folder is atomic, so a
  final path holds either the old file or the new one, never half of one; a rename also replaces a
  symlink instead of writing through it.
* **Ownership.** A command deletes only files it can prove it wrote. The proof is the format's own index
  file, written by the command last (``prediction.json`` lists its layers, ``dataset.yaml`` +
  ``manifest.csv`` list the patches, ``report.json`` its Markdown and plots): no extra file clutters a
  folder a GIS opens. Hidden ``.NAME.<tag>`` files of the command's own output names are its staging
  files (:meth:`OutputFolder.remove_leftovers`, done only under the folder's lock, so never those of a
  live run). ``overwrite`` lets a command replace the files at its own output names; it never removes
  other files or folders.
* **Inputs.** An output folder that equals or contains an input is refused (:func:`check_not_input`):
  replacing or cleaning it could destroy the input.
* **One writer at a time.** :class:`FolderLock`: an advisory lock file ``.aerialmtl.lock`` in the folder
  (``fcntl.flock``, held from the start to the end of the run and released by the kernel if the process
  dies), holding the holder's PID, host, command and torchrun job. A second process gets
  :class:`~aerialmtl.errors.OutputInUseError` naming the holder's PID. A lock file left by a process
  that died is taken over with a warning. Under ``torchrun`` the job's rank 0 takes the lock for the
  whole job; the other ranks write only after a barrier that rank 0 passes once it holds it. Where
  ``fcntl`` is missing (Windows) the lock is the exclusive creation of the lock file; one left by a
  killed process there must be deleted by hand (the message names it). The lock file is opened without
  following symlinks (a symlink in its place is refused: writing through it would truncate its target),
  and a forked child (a DataLoader worker, a multiprocessing pool) closes its copy at once, so the lock
  ends with the process that took it, not with the last of its children.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import shlex
import socket
import stat
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

from aerialmtl.errors import InputError, OutputError, OutputExistsError, OutputInUseError
from aerialmtl.filesafety import PARTIAL, atomic_write, special_file
from aerialmtl.io.oserrors import writing
from aerialmtl.io.paths import is_local

#: The lock file of an output folder (removed when the run ends).
LOCK_FILE = ".aerialmtl.lock"
#: Tag of a raster written block by block before its final form (``.NAME.staging``, ``.NAME.staging-<row>``
#: for one process's strip of rows).
STAGING = "staging"
#: Tag of the VRT that joins the strips of several processes (``.NAME.merge.vrt``).
MERGE_VRT = "merge.vrt"
#: Tags of hidden files a command may leave beside ``NAME`` while writing it (``.NAME.<tag>...``).
STAGING_TAGS = (PARTIAL, STAGING, MERGE_VRT)

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]  # no fcntl module on Windows: None says so


# ---- staging and atomic writes -------------------------------------------------------------------
def is_staging_of(path: Path, name: str) -> bool:
    """Whether ``path`` is a staging file of output ``name`` (``.NAME.<tag>`` with a tag of :data:`STAGING_TAGS`)."""
    return any(path.name.startswith(f".{name}.{tag}") for tag in STAGING_TAGS)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through its staging file; returns ``path``."""
    path = Path(path)
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def write_text(path: str | Path, text: str, what: str, atomic: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path``, a write error becoming an :class:`OutputError` naming it.

    Args:
        path: the file.
        text: its content.
        what: what it is, for the message (``"the QGIS style"``).
        atomic: replace ``path`` through its staging file; false when ``path`` is itself a staging file that
            the caller renames into place with the rest of its outputs.

    Returns:
        ``path``.
    """
    path = Path(path)
    with writing(path, what):
        if atomic:
            return write_text_atomic(path, text)
        path.write_text(text, encoding="utf-8")
    return path


# ---- inputs vs outputs ---------------------------------------------------------------------------
def is_local_path(path: str | Path) -> bool:
    """Whether ``path`` names a local file (not a URL or a GDAL virtual path; :func:`aerialmtl.io.paths.is_local`)."""
    return is_local(path)


def check_not_input(out: str | Path, inputs: Mapping[str, str | Path | None], option: str = "out_dir") -> None:
    """Refuse an output folder that equals or contains an input.

    Args:
        out: the output folder.
        inputs: parameter name → input path (``None`` and remote paths are skipped).
        option: the parameter naming ``out``.

    Raises:
        InputError: ``out`` is an input, or an input lies inside it (``param=option``).
    """
    resolved = Path(out).resolve()
    for param, path in inputs.items():
        if path is None or not is_local_path(path):
            continue
        p = Path(path).resolve()
        if p == resolved or resolved in p.parents:
            how = "is" if p == resolved else "contains"
            raise InputError(
                f"‹{option}› '{out}' {how} the input ‹{param}› '{path}': writing or cleaning it there could replace or "
                f"delete that input; choose another ‹{option}›", param=option)


def check_files_not_input(outputs: Iterable[str | Path],
                          inputs: Mapping[str, str | Path | None] | Iterable[tuple[str, str | Path | None]],
                          option: str = "out") -> None:
    """Refuse output files that are input files (writing them would replace the input).

    Args:
        outputs: the files a command will write.
        inputs: parameter name → input path (or such pairs; ``None`` and remote paths are skipped).
        option: the parameter naming the outputs.

    Raises:
        InputError: an output is one of ``inputs`` (``param=option``).
    """
    pairs = inputs.items() if isinstance(inputs, Mapping) else inputs
    given = {Path(p).resolve(): name for name, p in pairs if p is not None and is_local_path(p)}
    for out in outputs:
        name = given.get(Path(out).resolve())
        if name is not None:
            raise InputError(f"‹{option}› '{out}' would be written, but it is the input ‹{name}›; choose another "
                             f"‹{option}›", param=option)


def check_local_output(path: str | Path, option: str = "out_dir") -> None:
    """Refuse an output location that is a URL or a GDAL ``/vsi...`` path (outputs are written locally).

    Call it on the value as given: ``Path('s3://b/x')`` is already the local folder ``s3:/b/x``.

    Raises:
        OutputError: naming the parameter, the value and the fix.
    """
    if isinstance(path, str) and not is_local_path(path):
        raise OutputError(f"outputs must be local, but ‹{option}› '{path}' is a URL or GDAL virtual path; write to a "
                          "local folder and copy it up afterwards (e.g. `aws s3 sync FOLDER s3://bucket/prefix`)")


# ---- locks ---------------------------------------------------------------------------------------
def job_id() -> str | None:
    """The torchrun job this process belongs to (``None`` outside torchrun)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return None
    return (f"{os.environ.get('TORCHELASTIC_RUN_ID', '')}@{os.environ.get('MASTER_ADDR', '')}:"
            f"{os.environ.get('MASTER_PORT', '')}")


def is_job_leader() -> bool:
    """Whether this process takes locks for its job: a plain process, or rank 0 of a torchrun job."""
    return int(os.environ.get("WORLD_SIZE", "1")) <= 1 or os.environ.get("RANK", "0") == "0"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


#: Locks this process holds: resolved lock path → [count, fd]. Nested locks of one folder (the demo
#: running predict into its own folder) share one.
_HELD: dict[Path, list[int]] = {}


def _forget_locks_in_child() -> None:
    """In a forked child: close the inherited lock files.

    The parent keeps its locks; a ``flock`` lives as long as any process holds the file open, so a worker
    outliving a killed parent would hold it.
    """
    for _, fd in _HELD.values():
        with contextlib.suppress(OSError):
            os.close(fd)
    _HELD.clear()


if hasattr(os, "register_at_fork"):  # POSIX
    os.register_at_fork(after_in_child=_forget_locks_in_child)

def _owner(uid: int) -> str:
    """``user name (uid N)`` of ``uid`` (the number alone where the account is unknown)."""
    try:
        import pwd

        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except (ImportError, KeyError):
        return f"uid {uid}"


#: Flags of every open of a lock file: never through a symlink, never inherited by an exec'd program, never
#: blocking (on a FIFO put at its name).
_LOCK_OPEN_FLAGS = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NONBLOCK", 0)


class FolderLock:
    """The advisory lock of one output folder; see the module docstring.

    Args:
        folder: the folder (must exist).
        command: the command holding it (recorded for the message another process gets).
        option: the parameter naming the folder (for messages).
    """

    def __init__(self, folder: str | Path, command: str, option: str = "out_dir") -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self.command = command
        self.option = option
        self._key = self.path.resolve()

    def holder(self) -> dict[str, Any]:
        """What the lock file says about its holder (empty when unreadable)."""
        try:
            data = json.loads(self.path.read_text(encoding="utf-8") or "{}")
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    def _busy(self, holder: Mapping[str, Any]) -> OutputInUseError:
        who = f"aerialmtl {holder.get('command', '?')} (PID {holder.get('pid', '?')} on {holder.get('host', '?')}, " \
              f"started {holder.get('started', '?')})"
        return OutputInUseError(
            f"output folder '{self.folder}' is in use by {who}; wait for it to finish, stop it, or choose another "
            f"‹{self.option}›. If that process is gone, delete '{self.path}'")

    def _info(self) -> dict[str, Any]:
        return {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command,
                "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "job": job_id()}

    def _warn_stale(self, old: Mapping[str, Any]) -> None:
        if old.get("pid") is not None and old.get("pid") != os.getpid():
            warnings.warn(f"output folder '{self.folder}' was left locked by aerialmtl {old.get('command', '?')} "
                          f"(PID {old.get('pid')}), which stopped without releasing it; taking the lock over and "
                          "removing that run's unfinished files", stacklevel=4)

    def acquire(self) -> FolderLock:
        """Take the lock (or join this process's own hold on it).

        Raises:
            OutputInUseError: another process holds it.
            OutputError: the lock file cannot be created.
        """
        held = _HELD.get(self._key)
        if held is not None:
            held[0] += 1
            return self
        if self.path.is_symlink():
            raise OutputError(f"the lock file '{self.path}' is a symbolic link, which aerialmtl never writes (taking "
                              f"the lock through it would overwrite its target); delete the link, or choose another "
                              f"‹{self.option}›")
        kind = special_file(self.path)
        if kind is not None:  # opening a FIFO there would block forever; a folder cannot be locked
            raise OutputError(f"the lock file '{self.path}' is {kind}, not a regular file, which aerialmtl never "
                              f"makes; remove it (`rm -r {shlex.quote(str(self.path))}`) if nothing of yours needs it, "
                              f"or choose another ‹{self.option}›")
        try:
            fd = self._acquire_flock() if fcntl is not None else self._acquire_exclusive()
        except OSError as exc:
            if isinstance(exc, OutputInUseError):
                raise
            raise self._unwritable(exc) from exc
        _HELD[self._key] = [1, fd]
        return self

    def _unwritable(self, exc: OSError) -> OutputError:
        """The error for a lock file that cannot be created or replaced.

        A stale lock that this user may not replace (their own read-only one, another user's in a shared folder)
        is named as stale, with the command that removes it; otherwise the folder is not writable.
        """
        why = exc.strerror or str(exc)
        try:
            st = os.lstat(self.path)
        except OSError:
            st = None
        if st is None or not stat.S_ISREG(st.st_mode):
            return OutputError(f"cannot create the lock file '{self.path}' ({why}); choose a writable ‹{self.option}›")
        owner = _owner(st.st_uid)
        held = self._held_by_someone()
        state = ("is held by a running process" if held else
                 "is stale (no process holds it)" if held is False else "may be stale (it cannot be read to check)")
        fix = (f"remove it with `rm -f {shlex.quote(str(self.path))}`" + (
            f" (it belongs to {owner}: ask them, or an administrator, if you may not)"
            if hasattr(os, "geteuid") and st.st_uid != os.geteuid() else "")
            if not held else "wait for that run to finish")
        return OutputError(
            f"the lock file '{self.path}' left by an earlier run {state}, and you may not replace it ({why}; owned by "
            f"{owner}, mode {stat.filemode(st.st_mode)}); {fix}, or choose another ‹{self.option}›")

    def _held_by_someone(self) -> bool | None:
        """Whether a process holds the lock now (``None``: the file cannot be opened to tell)."""
        if fcntl is None:
            return None
        try:
            fd = os.open(self.path, os.O_RDONLY | _LOCK_OPEN_FLAGS)
        except OSError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        except OSError:
            return None
        finally:
            os.close(fd)
        return False

    def check_free(self) -> None:
        """Raise :class:`OutputInUseError` when another process holds the lock now (takes nothing).

        Lets a command name the process using the folder before it checks the folder's contents.
        """
        if _HELD.get(self._key) is not None or fcntl is None or not self.path.is_file():
            return
        try:
            fd = os.open(self.path, os.O_RDONLY | _LOCK_OPEN_FLAGS)
        except OSError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            raise self._busy(self.holder()) from None
        finally:
            os.close(fd)  # also releases the shared lock

    def _acquire_flock(self) -> int:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | _LOCK_OPEN_FLAGS, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise self._busy(self.holder()) from None
            except BaseException:
                os.close(fd)
                raise
            try:  # the holder before us may have removed the file between our open and our lock: retry
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        old = self.holder()
        self._warn_stale(old)
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(self._info()).encode())
        return fd

    def _acquire_exclusive(self) -> int:  # pragma: no cover - Windows
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | _LOCK_OPEN_FLAGS, 0o644)
        except FileExistsError:
            old = self.holder()
            pid = old.get("pid")
            if isinstance(pid, int) and old.get("host") == socket.gethostname() and not _alive(pid):
                self._warn_stale(old)
                with contextlib.suppress(OSError):
                    self.path.unlink()
                return self._acquire_exclusive()
            raise self._busy(old) from None
        os.write(fd, json.dumps(self._info()).encode())
        return fd

    def release(self) -> None:
        """Release the lock (the last of nested holds removes the lock file)."""
        held = _HELD.get(self._key)
        if held is None:
            return
        held[0] -= 1
        if held[0] > 0:
            return
        del _HELD[self._key]
        with contextlib.suppress(OSError):
            self.path.unlink()  # before unlocking, so nobody takes a lock on a file about to vanish
        with contextlib.suppress(OSError):
            os.close(held[1])

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


# ---- the output folder ---------------------------------------------------------------------------
def make_output_dir(path: str | Path, what: str = "output folder", option: str = "‹out_dir›") -> bool:
    """Create ``path`` (and its parents) if missing.

    Args:
        path: the folder.
        what: how the message calls it (``"run folder"``, ``"‹out_dir› folder"``, ...).
        option: the parameter that names it, as a mark (see :mod:`aerialmtl.errors`).

    Returns:
        True when this call created the folder (so a failed run may remove it again).

    Raises:
        OutputError: the folder cannot be created (a file in the way, no permission, ...).
    """
    path = Path(path)
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {what} '{path}' ({exc.strerror or exc}); choose a writable {option}") from exc
    return created


class OutputFolder:
    """A folder one command writes into, for the whole run (a context manager).

    Entering it refuses a folder that is an input or contains one, creates the folder if missing and
    takes its lock (:class:`FolderLock`; under torchrun only on rank 0, see :func:`is_job_leader`).
    Leaving it releases the lock and, when the run failed and the folder was created by it and holds
    nothing else, removes the folder again.

    Args:
        path: the folder.
        command: the command writing it (``"tile"``, ``"predict"``, ...).
        inputs: parameter name → input path that must not lie inside ``path``.
        option: the parameter naming the folder, for messages.
        what: how messages call the folder.
        lock: take the lock (off for a folder inside one this process already holds).
    """

    def __init__(self, path: str | Path, command: str, *, inputs: Mapping[str, str | Path | None] | None = None,
                 option: str = "out_dir", what: str = "output folder", lock: bool = True) -> None:
        check_local_output(path, option)
        self.path = Path(path)
        self.command = command
        self.option = option
        self.what = what
        self.inputs = dict(inputs or {})
        self.created = False
        self._lock = FolderLock(self.path, command, option) if lock and is_job_leader() else None

    def __enter__(self) -> OutputFolder:
        check_not_input(self.path, self.inputs, self.option)
        if self.path.exists() and not self.path.is_dir():
            raise OutputError(f"‹{self.option}› '{self.path}' is a file; pass a folder path")
        self.created = make_output_dir(self.path, self.what, f"‹{self.option}›")
        if self._lock is not None:
            try:
                self._lock.acquire()
            except BaseException:
                self._remove_if_created()
                raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._lock is not None:
            self._lock.release()
        if exc_type is not None:
            self._remove_if_created()

    def _remove_if_created(self) -> None:
        if self.created:
            with contextlib.suppress(OSError):
                self.path.rmdir()  # only when empty

    # ---- the files ---------------------------------------------------------------------------------
    def file(self, name: str) -> Path:
        """The path of ``name`` in the folder."""
        return self.path / name

    def existing(self, names: Iterable[str]) -> list[str]:
        """The ``names`` that exist in the folder (files, folders or links)."""
        return [n for n in names if os.path.lexists(self.path / n)]

    def claim(self, names: Iterable[str], overwrite: bool, *, fix: str = "") -> list[str]:
        """Check that the command may write ``names``; returns those that exist (to be replaced).

        Raises:
            OutputExistsError: some exist and ``overwrite`` is false.
            OutputError: one of them is a folder (``overwrite`` replaces files only).
        """
        existing = self.existing(names)
        folders = [n for n in existing if (self.path / n).is_dir() and not (self.path / n).is_symlink()]
        if folders:
            raise OutputError(f"{self.what} '{self.path}' holds a folder '{folders[0]}' where {self.command} writes a "
                              f"file; move it away or choose another ‹{self.option}›")
        if existing and not overwrite:
            raise OutputExistsError(
                f"{self.what} '{self.path}' already holds {', '.join(existing)}; pass ‹overwrite=True› to replace "
                f"{'it' if len(existing) == 1 else 'them'}{fix} or choose another ‹{self.option}›")
        return existing

    def remove_owned(self, names: Iterable[str]) -> None:
        """Remove files the caller proved this command wrote (listed in the format's index file)."""
        for name in names:
            path = self.path / name
            if path.is_file() or path.is_symlink():
                path.unlink()

    def remove_leftovers(self, names: Iterable[str]) -> list[Path]:
        """Remove hidden staging files of ``names`` (``.NAME.<tag>``) a killed run left; returns them.

        Called under the lock, so no live run of this folder owns them.
        """
        names = list(names)
        removed = []
        with contextlib.suppress(FileNotFoundError):
            for path in self.path.iterdir():
                if path.name.startswith(".") and any(is_staging_of(path, n) for n in names):
                    if path.is_dir() and not path.is_symlink():
                        _remove_tree(path)
                    else:
                        path.unlink(missing_ok=True)
                    removed.append(path)
        return removed


def _remove_tree(path: Path) -> None:
    """Remove a staging folder of this package (a hidden ``.NAME.partial`` folder and what is in it)."""
    import shutil

    shutil.rmtree(path, ignore_errors=True)


__all__ = ["LOCK_FILE", "MERGE_VRT", "STAGING", "STAGING_TAGS", "FolderLock", "OutputFolder", "check_local_output",
           "check_files_not_input", "check_not_input", "is_job_leader", "is_local_path", "is_staging_of", "job_id",
           "make_output_dir", "write_text", "write_text_atomic"]
