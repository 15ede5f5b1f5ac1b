"""The compiled part of :mod:`aerialmtl.models.class_kernel` (numba; imported only when a run needs it).

The functions are defined at module level so that numba's cache finds them again in the next process (a kernel
made inside a function is a new object in every process, and numba then compiled and cached it anew each time).

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
import numpy as np
from numba.core import caching

from aerialmtl import stores

log2e = np.float32(1.4426950408889634)
ln2_hi = np.float32(0.693359375)  # exactly representable, so that n·ln2_hi is exact
ln2_lo = np.float32(-2.12194440054690583e-4)  # ln 2 − ln2_hi
c2, c3, c4 = np.float32(1 / 2), np.float32(1 / 6), np.float32(1 / 24)
c5, c6, c7 = np.float32(1 / 120), np.float32(1 / 720), np.float32(1 / 5040)
one, half, zero = np.float32(1.0), np.float32(0.5), np.float32(0.0)
#: exp(d) for d below this is taken as exp of it (float32's smallest normal number is 1.2e-38 = exp(−87.3)).
EXP_FLOOR = np.float32(-87.0)

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
        super().__init__(folder, what="cached MC class kernel", env=_ENV, kind="numba kernel")
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
                        data = stores.read_file(path)
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
                         f"compiling the MC class kernel again (~1 s). If this repeats, clear the cache with "
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
                    data = stores.read_file(path)
                except OSError:
                    continue
                table[path.name] = hashlib.sha256(data or b"").hexdigest()
        self.write(MANIFEST, [json.dumps(table, sort_keys=True).encode()])


STORE = KernelStore(stores.open_store_folder("numba", "the MC class kernel"))


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


@jit
def add_row(zk: Any, img: int, y: int, p_sum: Any, e_sum: Any, top: Any, s_exp: Any, s_ed: Any,
            poly: Any, bits: Any, e: Any) -> None:  # pragma: no cover - runs compiled
    """One row of one sample: ``zk`` (K, W) logits → added into ``p_sum[:, img, y]`` and ``e_sum[img, y]``."""
    k_cls, width = zk.shape
    pow2 = bits.view(np.float32)
    for x in range(width):
        top[x] = zk[0, x]
    for k in range(1, k_cls):
        for x in range(width):
            v = zk[k, x]
            top[x] = v if v > top[x] else top[x]
    for x in range(width):
        s_exp[x] = zero
        s_ed[x] = zero
    for k in range(k_cls):
        for x in range(width):
            d = zk[k, x] - top[x]
            if d < EXP_FLOOR:  # NaN stays NaN
                d = EXP_FLOOR
            m = np.floor(d * log2e + half)
            r = (d - m * ln2_hi) - m * ln2_lo
            p = c7 * r + c6
            p = p * r + c5
            p = p * r + c4
            p = p * r + c3
            p = p * r + c2
            p = p * r + one
            poly[x] = p * r + one
            bits[x] = (np.int32(m) + np.int32(127)) << np.int32(23)
        for x in range(width):
            ex = poly[x] * pow2[x]
            e[k, x] = ex
            s_exp[x] += ex
            s_ed[x] += ex * (zk[k, x] - top[x])
    for x in range(width):
        inv = one / s_exp[x]
        h = np.log(s_exp[x]) - s_ed[x] * inv
        e_sum[img, y, x] += zero if h < zero else h  # clamped ≥ 0; NaN stays NaN
        s_exp[x] = inv
    for k in range(k_cls):
        for x in range(width):
            p_sum[k, img, y, x] += e[k, x] * s_exp[x]


@jit
def kernel(z: Any, b: int, p_sum: Any, e_sum: Any, channels_last: bool) -> None:  # pragma: no cover
    """:func:`aerialmtl.models.class_kernel.add_class_sums` (its arguments), row by row of every sample."""
    if channels_last:  # (N, H, W, K): each row is copied into class planes first (K × W, in the cache)
        n_img, height, width, k_cls = z.shape
    else:  # (N, K, H, W)
        n_img, k_cls, height, width = z.shape
    top = np.empty(width, np.float32)
    s_exp = np.empty(width, np.float32)
    s_ed = np.empty(width, np.float32)
    poly = np.empty(width, np.float32)
    bits = np.empty(width, np.int32)
    e = np.empty((k_cls, width), np.float32)
    planes = np.empty((k_cls, width), np.float32)
    for n in range(n_img):
        img = n % b
        for y in range(height):
            if channels_last:
                for x in range(width):
                    for k in range(k_cls):
                        planes[k, x] = z[n, y, x, k]
                add_row(planes, img, y, p_sum, e_sum, top, s_exp, s_ed, poly, bits, e)
            else:
                add_row(z[n, :, y, :], img, y, p_sum, e_sum, top, s_exp, s_ed, poly, bits, e)


__all__ = ["EXP_FLOOR", "MANIFEST", "STORE", "GuardedCache", "KernelStore", "add_row", "jit", "kernel"]
