"""Every store the package keeps heals (issue 40, item 1): the numba kernel's store and the OpenVINO cache, read or
written with a damaged, empty, foreign, non-regular or unwritable entry, mean "rebuild or run without it" with one
warning naming the path and the fix; never a crash, a hang or a Ctrl-C exit status. A full ``$TMPDIR`` (a real
tmpfs) names the temporary folder, not the model. The stores live in the platform's cache folder (never in the
package, never at ``/`` for an empty HOME), stay within a size bound, and ``aerialmtl cache`` lists and clears them.

Most cases run ``python -m aerialmtl`` in a new process: a store is opened once per process, as for a user.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rasterio
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.procs import OTHER_UID, aerialmtl, env, one_line, other_user_or_skip
from helpers.rasters import write_raster
from helpers.tmpfs import mount_tmpfs

from aerialmtl import stores
from aerialmtl.formats.checkpoint import save_checkpoint

BAD = ("Error: unexpected", "Aborted", "Traceback")


@pytest.fixture(scope="module")
def shared() -> Iterator[Path]:
    """A folder every user can enter (the permission cases run as another user; pytest's tmp_path is private)."""
    folder = Path(tempfile.mkdtemp(prefix="aerialmtl-stores-", dir="/tmp"))
    folder.chmod(0o777)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def inputs(shared: Path) -> tuple[Path, Path]:
    """A tiny checkpoint and orthophoto, readable by every user."""
    model, meta = tiny_d3net()
    save_checkpoint(shared / "m.pt", model, meta)
    rng = np.random.default_rng(40)
    ortho = write_raster(shared / "o.tif", rng.integers(1, 256, size=(3, 40, 56)).astype(np.uint8))
    for p in (shared / "m.pt", ortho):
        p.chmod(0o644)
    return shared / "m.pt", ortho


def _predict(inputs: tuple[Path, Path], out: Path, cache: Path, *extra: object, engine: str = "torch",
             as_other_user: bool = False, **environ: str):
    ckpt, ortho = inputs
    e = env(AERIALMTL_CACHE=str(cache), AERIALMTL_OPENVINO_CACHE=str(cache / "openvino"), **environ)
    return aerialmtl("predict", ortho, "--model", ckpt, "--out", out, "--mc", "2", "--window", "32", "--overlap",
                     "8", "--engine", engine, *extra, environ=e, timeout=600, as_other_user=as_other_user)


def _heights(out: Path) -> np.ndarray:
    with rasterio.open(out / "height.tif") as src:
        return src.read(1)


@pytest.fixture(scope="module")
def warm(inputs: tuple[Path, Path], shared: Path) -> tuple[Path, np.ndarray]:
    """A numba store after one MC prediction (the template every damage case copies), and that run's heights."""
    cache = shared / "warm-cache"
    done = _predict(inputs, shared / "warm-out", cache)
    assert done.returncode == 0, done.stderr
    return cache / "numba", _heights(shared / "warm-out")


# ---- the numba kernel's store -------------------------------------------------------------------------------
def test_numba_kernel_is_cached_in_the_package_store_not_in_the_package(warm: tuple[Path, np.ndarray]) -> None:
    folder, _ = warm
    names = sorted(p.name for p in folder.iterdir())
    assert any(n.endswith(".nbi") for n in names) and any(n.endswith(".nbc") for n in names) and "manifest" in names
    package = Path(__file__).resolve().parents[1] / "aerialmtl" / "models" / "__pycache__"
    started = time.time() - 3600
    assert not [p for p in package.glob("class_kernel_jit*.nb*") if p.stat().st_mtime > started]


def _damage(folder: Path, how: str) -> Path:
    """Damage one file of a numba store as ``how`` says; returns the path damaged."""
    nbi = sorted(folder.glob("class_kernel_jit.kernel-*.nbi"))[0]
    nbc = sorted(folder.glob("class_kernel_jit.kernel-*.nbc"))[0]
    if how == "random-index":
        nbi.write_bytes(os.urandom(nbi.stat().st_size))
        return nbi
    if how == "empty-index":  # what a power loss leaves
        nbi.write_bytes(b"")
        return nbi
    if how == "truncated-data":
        nbc.write_bytes(nbc.read_bytes()[:100])
        return nbc
    if how == "fifo-index":
        nbi.unlink()
        os.mkfifo(nbi)
        return nbi
    if how == "foreign-data":  # another user's file (a pickle: code the run would execute)
        os.chown(nbc, OTHER_UID, OTHER_UID)
        return nbc
    if how == "manifest-edited":
        (folder / "manifest").write_bytes(b"garbage")
        return folder / "manifest"
    raise AssertionError(how)


@pytest.mark.parametrize("how", ["random-index", "empty-index", "truncated-data", "fifo-index", "foreign-data",
                                 "manifest-edited"])
def test_damaged_numba_store_is_rebuilt_with_one_warning(how: str, warm: tuple[Path, np.ndarray], inputs,
                                                          shared: Path) -> None:
    if how == "foreign-data" and os.geteuid() != 0:
        pytest.skip("needs root to give a file to another user")
    template, reference = warm
    cache = shared / f"cache-{how}"
    shutil.copytree(template, cache / "numba")
    bad = _damage(cache / "numba", how)
    done = _predict(inputs, shared / f"out-{how}", cache)  # a FIFO read would block: the timeout says "hang"
    err = one_line(done.stderr)
    assert done.returncode == 0, err
    assert not any(b in err for b in BAD)
    assert f"'{bad}'" in err and "aerialmtl cache clear --store numba" in err
    assert err.count("warning: the numba kernel cache held") == 1
    np.testing.assert_array_equal(_heights(shared / f"out-{how}"), reference)
    assert not stat.S_ISFIFO(os.lstat(bad).st_mode) if bad.exists() else True
    again = _predict(inputs, shared / f"out2-{how}", cache)  # healed: the next run is quiet
    assert again.returncode == 0 and "warning" not in again.stderr, again.stderr


def test_unwritable_numba_store_predicts_with_a_warning_as_another_user(inputs, shared: Path,
                                                                         warm: tuple[Path, np.ndarray]) -> None:
    foreign = other_user_or_skip()
    cache = shared / "foreign-cache"  # 0755, owned by another user: the run can read it, not write it
    cache.mkdir(mode=0o755)
    os.chown(cache, foreign, foreign)
    out = shared / "out-other-user"
    done = _predict(inputs, out, cache, as_other_user=True, HOME=str(shared))
    err = one_line(done.stderr)
    assert done.returncode == 0, err
    assert not any(b in err for b in BAD)
    assert f"the numba kernel cache folder '{cache / 'numba'}' cannot be written (Permission denied)" in err
    assert "AERIALMTL_CACHE=/a/writable/folder" in err
    np.testing.assert_array_equal(_heights(out), warm[1])


# ---- the OpenVINO engine's store --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ov_warm(inputs, shared: Path) -> tuple[Path, np.ndarray]:
    pytest.importorskip("openvino")
    cache = shared / "ov-warm"
    done = _predict(inputs, shared / "ov-warm-out", cache, engine="openvino")
    assert done.returncode == 0, done.stderr
    return cache, _heights(shared / "ov-warm-out")


@pytest.mark.parametrize("how", ["fifo", "foreign", "symlink", "folder"])
def test_non_regular_or_foreign_openvino_entries_are_rebuilt(how: str, ov_warm, inputs, shared: Path) -> None:
    if how == "foreign" and os.geteuid() != 0:
        pytest.skip("needs root to give a file to another user")
    template, reference = ov_warm
    cache = shared / f"ov-{how}"
    shutil.copytree(template, cache, symlinks=True)
    entries = sorted(p for p in (cache / "openvino").rglob("*") if p.is_file() and p.suffix in (".ir", ".blob"))
    assert entries
    for p in entries:
        if how == "foreign":
            os.chown(p, OTHER_UID, OTHER_UID)
            continue
        p.unlink()
        if how == "fifo":
            os.mkfifo(p)
        elif how == "symlink":
            p.symlink_to(inputs[0])
        else:
            p.mkdir()
    done = _predict(inputs, shared / f"ov-out-{how}", cache, engine="openvino")  # a hang fails on the timeout
    err = one_line(done.stderr)
    assert done.returncode == 0, err
    assert not any(b in err for b in BAD)
    word = {"fifo": "a FIFO, not a regular file", "foreign": "owned by another user", "symlink": "a symbolic link",
            "folder": "a folder, not a regular file"}[how]
    # the first entry read is named (with a folder there, caching then stops: later entries are not read)
    assert any(f"cached OpenVINO model '{p}' is {word}" in err for p in entries), err
    if how == "folder":  # a folder at an entry's name cannot be replaced: caching is off, the run goes on
        assert "cannot be written" in err, err
    np.testing.assert_array_equal(_heights(shared / f"ov-out-{how}"), reference)


@pytest.fixture
def full_tmpdir(shared: Path) -> Iterator[Path]:
    """A real tmpfs of 256 KiB with 24 KiB left: ``$TMPDIR`` with room for Python's probe file (completely full,
    ``tempfile`` would quietly use /tmp instead) but not for the converted model (root only, else skipped).
    """
    folder = Path(tempfile.mkdtemp(dir=shared))
    folder.rmdir()
    for mounted in mount_tmpfs(folder, "size=256k,mode=1777"):
        (mounted / "filler").write_bytes(b"\0" * 232 * 1024)
        yield mounted


@pytest.mark.parametrize("engine", ["openvino", "auto"])
def test_full_tmpdir_names_the_temporary_folder_not_the_model(engine: str, full_tmpdir: Path, ov_warm, inputs,
                                                              shared: Path) -> None:
    cache = shared / f"tmpdir-{engine}"  # a cold cache: the model is converted and serialised through $TMPDIR
    out = shared / f"tmpdir-out-{engine}"
    done = _predict(inputs, out, cache, engine=engine, TMPDIR=str(full_tmpdir))
    err = one_line(done.stderr)
    assert done.returncode == 0, err
    choice = json.loads((out / "prediction.json").read_text())["engine_choice"]
    if engine == "auto" and "cache cold" in choice["reason"]:  # a measured CPU kind: torch for a job this small
        assert choice["engine"] == "torch" and "cannot run this model" not in err
        return
    assert not any(b in err for b in BAD) and "Error:" not in err  # OpenVINO's "iostream error" only as the cause
    assert f"the temporary folder '{full_tmpdir}' ($TMPDIR={full_tmpdir}" in err and "point TMPDIR at" in err
    assert "cannot run this model" not in err  # the model runs: it was the temporary folder
    assert json.loads((out / "prediction.json").read_text())["engine"] == "openvino"
    np.testing.assert_array_equal(_heights(out), ov_warm[1])


# ---- where the stores live, their size, the cache command -----------------------------------------------------
@pytest.mark.parametrize("home", ["", "/"])
def test_empty_or_root_home_never_caches_at_the_file_system_root(home: str, shared: Path) -> None:
    e = env(HOME=home)
    for key in ("AERIALMTL_CACHE", "AERIALMTL_OPENVINO_CACHE", "XDG_CACHE_HOME"):
        e.pop(key, None)
    done = aerialmtl("cache", "list", environ=e)
    assert done.returncode == 0, done.stderr
    import pwd

    account_home = pwd.getpwuid(os.geteuid()).pw_dir
    assert f"{account_home.rstrip('/')}/.cache/aerialmtl/numba" in done.stdout
    assert " /.cache" not in done.stdout


def test_no_home_at_all_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    import pwd

    class Entry:
        pw_dir = "/"

    monkeypatch.setattr(pwd, "getpwuid", lambda uid: Entry())
    for key in ("AERIALMTL_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("HOME", "")
    code, _, err = run_cli(capsys, "cache", "list")
    assert code == 1 and "HOME is '', which is no home folder" in err and "AERIALMTL_CACHE=" in err
    assert stores.open_store_folder("numba", "the kernel") is None  # a run goes on without the store


def test_stores_evict_least_recently_used_beyond_the_size_limit(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AERIALMTL_CACHE", str(tmp_path / "c"))
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(tmp_path / "c" / "openvino"))
    monkeypatch.setenv("AERIALMTL_CACHE_LIMIT_MB", "1")
    store = stores.Store(tmp_path / "c" / "openvino" / "model", "cached OpenVINO model")
    block = [os.urandom(300 * 1024)]
    for n, name in enumerate(("a", "b", "c")):
        store.write(name, block)
        os.utime(store.path(name), (1000 + n, 1000 + n))  # written in this order, long ago
    assert store.read("a") is not None  # a use: "a" is now the most recently used
    stores.reset_warnings()
    with pytest.warns(UserWarning, match="removed 1 least recently used entry"):
        store.write("d", block)  # 4 × 300 KiB > 1 MiB: the least recently used ("b") goes
    assert sorted(p.name for p in store.folder.iterdir()) == ["a", "c", "d"]
    monkeypatch.setenv("AERIALMTL_CACHE_LIMIT_MB", "0")
    stores.reset_warnings()  # a command says it once: the next command again
    with pytest.warns(UserWarning, match="removed 3 least recently used entries"):
        store.write("e", block)  # the entry just written stays, even alone beyond the limit
    assert sorted(p.name for p in store.folder.iterdir()) == ["e"]


def test_cache_command_lists_and_clears(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                        capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setenv("AERIALMTL_CACHE", str(tmp_path / "c"))
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(tmp_path / "c" / "openvino"))
    stores.Store(tmp_path / "c" / "openvino" / "m").write("forward.ir", [b"x" * 2048])
    stores.Store(tmp_path / "c" / "numba").write("manifest", [b"{}"])
    code, out, err = run_cli(capsys, "cache")
    assert code == 0, err
    assert "openvino      1 file(s)" in out and str(tmp_path / "c" / "openvino") in out
    assert "numba         1 file(s)" in out and "AERIALMTL_CACHE_LIMIT_MB" in out
    code, out, _ = run_cli(capsys, "cache", "clear", "--store", "openvino")
    assert code == 0 and "removed 1 file(s)" in out
    assert not list((tmp_path / "c" / "openvino").rglob("*.ir")) and (tmp_path / "c" / "numba" / "manifest").exists()
    code, out, _ = run_cli(capsys, "cache", "clear")
    assert code == 0 and not [p for p in (tmp_path / "c").rglob("*") if p.is_file()]


@pytest.mark.parametrize("how", ["empty", "fifo", "symlink", "zeroed", "edited"])
def test_store_entries_are_checked_before_use(how: str, tmp_path: Path) -> None:
    store = stores.Store(tmp_path / "s", "cached thing")
    store.write("e", [b"payload" * 100])
    path = store.path("e")
    if how == "empty":
        path.write_bytes(b"")
    elif how == "fifo":
        path.unlink()
        os.mkfifo(path)
    elif how == "symlink":
        path.unlink()
        path.symlink_to("/etc/hostname")
    elif how == "zeroed":
        path.write_bytes(bytes(path.stat().st_size))
    else:
        data = bytearray(path.read_bytes())
        data[-1] ^= 1
        path.write_bytes(bytes(data))
    stores.reset_warnings()
    with pytest.warns(UserWarning, match=f"cached thing '{path}' is .*; rebuilding it"):
        assert store.read("e") is None
    assert not path.exists() and not path.is_symlink()
    store.write("e", [b"again"])
    assert store.read("e") == [b"again"]


# ---- a store owns only what it wrote (issue 49) ------------------------------------------------------------
def _user_folder(folder: Path) -> dict[Path, bytes]:
    """A project folder of a user's own files (what AERIALMTL_OPENVINO_CACHE was pointed at by mistake): files at
    the top, in a subfolder and deeper, one of them named like an entry; returns path → content."""
    files = {folder / "mosaic.tif": os.urandom(300 * 1024), folder / "survey" / "a.las": os.urandom(200 * 1024),
             folder / "survey" / "forward.ir": b"my own file " * 1000,
             folder / "deep" / "er" / "b.laz": os.urandom(100 * 1024), folder / "manifest": b"{}"}
    for path, data in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        os.utime(path, (1000, 1000))  # older than every entry: first in line, were they entries
    return files


def test_eviction_and_clear_leave_a_users_files_in_the_store_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                    capsys: pytest.CaptureFixture) -> None:
    """AERIALMTL_OPENVINO_CACHE pointed at a project folder and a tiny limit: eviction removes only entries the
    store wrote (saying so), `cache list` does not count the user's files, `cache clear` leaves them."""
    project = tmp_path / "project"
    mine = _user_folder(project)
    monkeypatch.setenv("AERIALMTL_CACHE", str(tmp_path / "c"))
    monkeypatch.setenv("AERIALMTL_OPENVINO_CACHE", str(project))
    monkeypatch.setenv("AERIALMTL_CACHE_LIMIT_MB", "0.5")
    store = stores.Store(project / "0123456789abcdef01234567", "cached OpenVINO model")
    stores.reset_warnings()
    with pytest.warns(UserWarning) as seen:
        for name in ("forward.ir", "decode.ir", "encode.ir"):
            store.write(name, [os.urandom(200 * 1024)])
    messages = [str(w.message) for w in seen]
    assert len(messages) == 1 and "removed 1 least recently used entry of their own" in messages[0], messages
    assert f"'{store.path('forward.ir')}'" in messages[0] and "AERIALMTL_CACHE_LIMIT_MB" in messages[0]
    for path, data in mine.items():
        assert path.read_bytes() == data, path
    assert sorted(p.name for p in store.folder.iterdir()) == ["decode.ir", "encode.ir"]
    code, out, err = run_cli(capsys, "cache", "list", "--store", "openvino")
    assert code == 0, err
    assert "openvino      2 file(s)" in out and "0.4 MiB" in out
    assert "and 4 other file(s), not aerialmtl's" in out  # the deep one is not even looked at
    code, out, err = run_cli(capsys, "cache", "clear", "--store", "openvino")
    assert code == 0, err
    assert "removed 2 file(s), 0.4 MiB" in out and "left 4 other file(s) there, which aerialmtl did not write" in out
    assert not store.folder.exists()  # the model folder it emptied goes; the project folder and its files stay
    for path, data in mine.items():
        assert path.read_bytes() == data, path


def test_numba_store_heals_only_numba_files(warm: tuple[Path, np.ndarray], inputs, shared: Path) -> None:
    """A user's file in the numba store's folder is not numba's: a run neither removes nor warns about it, and the
    cache command leaves it."""
    template, reference = warm
    cache = shared / "cache-user-file"
    shutil.copytree(template, cache / "numba")
    notes = cache / "numba" / "notes.txt"
    notes.write_text("mine")
    done = _predict(inputs, shared / "out-user-file", cache)
    assert done.returncode == 0 and "warning" not in done.stderr, done.stderr
    np.testing.assert_array_equal(_heights(shared / "out-user-file"), reference)
    assert notes.read_text() == "mine"
    e = env(AERIALMTL_CACHE=str(cache), AERIALMTL_OPENVINO_CACHE=str(cache / "openvino"))
    listed = aerialmtl("cache", "list", "--store", "numba", environ=e)
    assert listed.returncode == 0 and "and 1 other file(s)" in listed.stdout, listed.stdout + listed.stderr
    cleared = aerialmtl("cache", "clear", "--store", "numba", environ=e)
    assert cleared.returncode == 0 and "left 1 other file(s)" in cleared.stdout, cleared.stdout + cleared.stderr
    assert sorted(p.name for p in (cache / "numba").iterdir()) == ["notes.txt"]


def test_two_predicts_filling_a_tiny_store_at_once_both_complete_with_the_same_maps(ov_warm, inputs,
                                                                                  shared: Path) -> None:
    """A store of 0 MiB: every write of either run evicts the other's entries (only entries: a user's file there
    stays). Both runs complete, with the maps of a run on a warm cache (fp32 tolerance of the engine tests)."""
    import subprocess
    import sys

    _, reference = ov_warm
    cache = shared / "tiny-shared"
    (cache / "openvino").mkdir(parents=True)
    (cache / "openvino" / "mosaic.tif").write_bytes(b"mine" * 1000)
    ckpt, ortho = inputs
    e = env(AERIALMTL_CACHE=str(cache), AERIALMTL_OPENVINO_CACHE=str(cache / "openvino"), AERIALMTL_CACHE_LIMIT_MB="0")
    runs = [subprocess.Popen([sys.executable, "-m", "aerialmtl", "predict", ortho, "--model", ckpt, "--out",
                              shared / f"tiny-out-{n}", "--mc", "2", "--window", "32", "--overlap", "8", "--engine",
                              "openvino"], env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for n in range(2)]
    for run in runs:
        _, err = run.communicate(timeout=900)
        assert run.returncode == 0, err
        assert not any(b in err for b in BAD), err
    for n in range(2):
        np.testing.assert_allclose(_heights(shared / f"tiny-out-{n}"), reference, rtol=0, atol=1e-4)
    assert (cache / "openvino" / "mosaic.tif").read_bytes() == b"mine" * 1000
