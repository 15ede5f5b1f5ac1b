"""numba kernels whose machine code is kept in the package's ``numba`` store: :func:`jit`.

The package's compiled kernels (the MC class kernel, :mod:`aerialmtl.models.class_kernel_jit`; the shadow
step's kernels, :mod:`aerialmtl.sun.kernels`; a CPU run's training batches, :mod:`aerialmtl.data.assemble`) are
``numba.njit`` functions defined at module level, so that numba's cache finds them again in the next process (a
kernel made inside a function is a new object in every process, and numba then compiled and cached it anew each
time). Importing this module imports numba (~0.3 s): modules that use
it are imported only when a run needs their kernels.

The machine code is kept in the package's ``numba`` store (:func:`aerialmtl.stores.store_folder`; e.g.
``~/.cache/aerialmtl/numba``), never in the installed package's ``__pycache__`` (read-only in a system install,
and shared by every user of it), under the stores' rule (:mod:`aerialmtl.stores`): numba's files are pickles, so
they are loaded only when they are regular files of this user whose SHA-256 matches the one recorded when they
were written (the ``manifest`` entry, itself checksummed); anything else in the folder (damaged, empty, edited,
foreign, a FIFO, a link) is removed with one warning before numba reads it, and recompiled (~1 s). A load that
fails anyway (:class:`GuardedCache`) is a recompile with a warning, a folder that cannot be written a run
without the cache with a warning: never a failed prediction, a hang or a Ctrl-C exit status.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import threading
from pathlib import Path
from typing import Any

import numba
from numba.core import caching

from aerialmtl import filesafety, stores

_OPTIONS: dict[str, Any] = {"boundscheck": False, "error_model": "numpy", "nogil": True}
#: The entry recording the SHA-256 of every file numba wrote in the store.
MANIFEST = stores.MANIFEST
#: The names numba gives its files: ``<module>.<function>-<line>.py<version>.nbi`` (the index) and
#: ``....<n>.nbc`` (the machine code), and ``<either>.tmp.<hex>`` while it writes one. Only such files are
#: numba's: any other file in the folder is a user's, never read, judged or removed.
NUMBA_FILE = re.compile(r"^[\w.]+-\d+\.py\w+?(\.\d+\.nbc|\.nbi)(\.tmp\.[0-9a-f]+)?$")
#: The environment variable that moves the store (every store: :data:`aerialmtl.stores.ROOT_ENV`).
_ENV = stores.ROOT_ENV


class KernelStore(stores.Store):
    """The ``numba`` store: numba's own files, trusted through the checksummed :data:`MANIFEST`.

    Args:
        folder: the store's folder, or ``None`` (nothing cached).
    """

    def __init__(self, folder: Path | None) -> None:
        super().__init__(folder, what="cached numba kernel", env=_ENV, kind="numba kernel")
        self._healed = False
        self._lock = threading.Lock()

    def usable(self) -> bool:
        """Whether the folder exists or can be made, and takes a file (else the store is off, with a warning)."""
        if self.folder is None:
            return False
        probe = self.folder / f".probe.{os.getpid()}"
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            stores.remove_entry(probe)
            self.disable(exc, "written")
            return False
        return True

    def _files(self) -> list[Path]:
        """The files of numba's in the folder (:data:`NUMBA_FILE`; its staging files too, not the manifest)."""
        assert self.folder is not None
        try:
            names = os.listdir(self.folder)
        except OSError:
            return []
        return [self.folder / n for n in sorted(names) if NUMBA_FILE.match(n)]

    def _recorded(self) -> dict[str, str]:
        found = self.read(MANIFEST)
        if found is None:
            return {}
        try:
            table = json.loads(found[0])
            if not (isinstance(table, dict) and all(isinstance(v, str) for v in table.values())):
                raise ValueError("not a table of checksums")
        except ValueError:
            self.problem(self.path(MANIFEST), "not aerialmtl's record of the kernel's files")
            return {}
        return table

    def heal(self) -> None:
        """Remove every file numba would read that is not one it wrote here (see the module docstring).

        One warning names them; once per process, before numba reads the folder.
        """
        with self._lock:
            if self._healed or self.folder is None:
                return
            self._healed = True
            recorded = self._recorded()
            bad: list[tuple[Path, str]] = []
            for path in self._files():
                if ".tmp." in path.name:  # numba's own staging file, left by a killed process
                    stores.remove_entry(path)
                    continue
                why = stores.entry_problem(path)
                if why is None:
                    want = recorded.get(path.name)
                    try:
                        data = filesafety.read_file(path)
                    except OSError as exc:
                        why = f"unreadable ({exc.strerror or exc})"
                    else:
                        have = hashlib.sha256(data or b"").hexdigest()
                        why = None if have == want else "not the file aerialmtl recorded (damaged, edited " \
                            "or written by someone else)" if want else "not one aerialmtl recorded"
                if why is not None:
                    bad.append((path, why))
            self.discard(bad)

    def discard(self, bad: list[tuple[Path, str]]) -> None:
        """Remove files ``bad`` (path, why) with one warning naming them; numba then recompiles (~1 s)."""
        if not bad:
            return
        for path, _ in bad:
            stores.remove_entry(path)
        listed = "; ".join(f"'{path}' is {why}" for path, why in bad[:4]) + ("; ..." if len(bad) > 4 else "")
        stores.warn_once(f"the numba kernel cache held {len(bad)} file(s) it cannot use ({listed}); removed them and "
                         f"compiling the kernels again (~1 s). If this repeats, clear the cache with "
                         f"`aerialmtl cache clear --store numba`, or move it with {_ENV}=/a/writable/folder",
                         stacklevel=6)

    def record(self) -> None:
        """Record the SHA-256 of numba's files as they are now (after numba wrote some)."""
        if self.folder is None:
            return
        table = {}
        for path in self._files():
            if stores.entry_problem(path) is None and ".tmp." not in path.name:
                try:
                    data = filesafety.read_file(path)
                except OSError:
                    continue
                table[path.name] = hashlib.sha256(data or b"").hexdigest()
        self.write(MANIFEST, [json.dumps(table, sort_keys=True).encode()])


STORE = KernelStore(stores.open_store_folder("numba", "the compiled kernels"))


class _Locator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """The numba cache locator pointing at the package's ``numba`` store (freshness: the hash of this file)."""

    def __init__(self, py_func: Any, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno

    def ensure_cache_path(self) -> None:
        assert STORE.folder is not None
        STORE.folder.mkdir(parents=True, exist_ok=True)

    def get_cache_path(self) -> str:
        assert STORE.folder is not None
        return str(STORE.folder)

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> _Locator:
        return cls(py_func, py_file)


class _Impl(caching.CompileResultCacheImpl):
    _locator_classes = [_Locator]


class GuardedCache(caching.FunctionCache):
    """numba's function cache in the ``numba`` store, under the stores' rule.

    The folder is healed before the first load, a load that fails anyway is a recompile (with a warning), a save
    that fails turns caching off (with a warning), and every save is recorded in the manifest.
    """

    _impl_class = _Impl

    def load_overload(self, sig: Any, target_context: Any) -> Any:
        """Numba's load (healed first); ``None`` (compile again) when the files cannot be loaded after all."""
        STORE.heal()
        if STORE.folder is None:
            return None
        try:
            return super().load_overload(sig, target_context)  # type: ignore[no-untyped-call]  # numba: unannotated
        except Exception as exc:  # damaged pickles raise anything: UnpicklingError, EOFError, ValueError, ...
            why = f"not loadable ({type(exc).__name__}: {' '.join(str(exc).split()) or 'no detail'})"
            STORE.discard([(path, why) for path in STORE._files()])
            return None

    def save_overload(self, sig: Any, data: Any) -> None:
        """Numba's save, recorded in the manifest; a folder that cannot take it turns caching off."""
        if STORE.folder is None:
            return
        try:
            super().save_overload(sig, data)  # type: ignore[no-untyped-call]  # numba: unannotated
        except OSError as exc:
            STORE.disable(exc, "written")
            self.disable()  # type: ignore[no-untyped-call]  # numba: unannotated
            return
        STORE.record()


def jit(fn: Any) -> Any:
    """``numba.njit`` with its cache in the package's ``numba`` store (see the module docstring); where the store
    cannot be written the function is compiled in every process instead (~1 s), with one warning, rather than not
    run.
    """
    dispatcher = numba.njit(cache=False, **_OPTIONS)(fn)
    if STORE.usable():
        # numba's Dispatcher.enable_caching, with this cache class
        dispatcher._cache = GuardedCache(fn)  # type: ignore[no-untyped-call]  # numba: unannotated
    return dispatcher


__all__ = ["MANIFEST", "NUMBA_FILE", "STORE", "GuardedCache", "KernelStore", "jit"]
