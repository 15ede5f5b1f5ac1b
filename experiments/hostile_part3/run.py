"""The hostile pass of issue 40 (part 3): each case run as a user runs it, ``python -m aerialmtl ...`` in a new
process, around the stores, sidecars, remote inputs, schemas, locks and the QGIS provider.

Usage (from the repository root)::

    PYTHONPATH=. nice -n 10 python -m experiments.hostile_part3.run WORKDIR > experiments/hostile_part3/results.jsonl

One JSON line per case: name, command, exit status, seconds, the last lines of stderr/stdout, and the automatic
checks (no "Error: unexpected", no traceback, no "Aborted", no hang: a case that passes its timeout is a hang). The
verdicts in experiments/hostile_part3/README.md are read from these lines.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import rasterio
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from helpers.models import tiny_d3net  # noqa: E402
from helpers.rasters import write_raster  # noqa: E402

from aerialmtl.formats.checkpoint import save_checkpoint  # noqa: E402
from aerialmtl.qgis_plugin.spec import ALGORITHMS, command_line  # noqa: E402

W = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/tmp/hostile3")
BASE_ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "AERIALMTL_PROGRESS": "json",
            "AERIALMTL_CACHE": str(W / "cache"), "AERIALMTL_OPENVINO_CACHE": str(W / "cache" / "openvino")}
_PRINT = threading.Lock()
NO_OVERRIDE = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search,-fowner"]
ARGS = ["--window", "64", "--overlap", "16", "--engine", "torch", "--mc", "2"]


def run(name: str, args: list[str], env: dict[str, str] | None = None, prefix: list[str] | None = None,
        timeout: float = 400, cwd: Path | None = None) -> dict:
    """Run ``python -m aerialmtl ARGS``; print and return the case's record."""
    cmd = [*(prefix or []), sys.executable, "-m", "aerialmtl", *map(str, args)]
    e = dict(BASE_ENV)
    e.update(env or {})
    e = {k: v for k, v in e.items() if v is not None}
    t0 = time.monotonic()
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, env=e, timeout=timeout, cwd=cwd, check=False)
        rc, out, err = done.returncode, done.stdout, done.stderr
    except subprocess.TimeoutExpired as exc:
        rc, out, err = "HANG", str(exc.stdout or ""), str(exc.stderr or "")
    err_lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("{")]
    rec = {"case": name, "cmd": " ".join(shlex.quote(str(c)) for c in cmd[len(prefix or []) + 1:]),
           "env": {k: v for k, v in (env or {}).items()}, "prefix": " ".join(prefix or []), "rc": rc,
           "s": round(time.monotonic() - t0, 1), "stderr": err_lines[-4:], "stdout": out.strip().splitlines()[-2:],
           "unexpected": "Error: unexpected" in err, "traceback": "Traceback" in err, "aborted": "Aborted" in err}
    with _PRINT:
        print(json.dumps(rec), flush=True)
    return rec


def fresh(name: str) -> Path:
    path = W / name
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path


def main() -> None:  # noqa: C901, PLR0915 - one list of cases, read top to bottom
    if set(sys.argv[1:]) & {"-h", "--help"}:
        print(__doc__)
        return
    shutil.rmtree(W, ignore_errors=True)
    W.mkdir(parents=True)
    os.chmod(W, 0o777)
    model, meta = tiny_d3net()
    ckpt = W / "m.pt"
    save_checkpoint(ckpt, model, meta)
    rng = np.random.default_rng(3)
    ortho = write_raster(W / "o.tif", rng.integers(1, 256, size=(3, 48, 64)).astype(np.uint8))
    P = ["predict", ortho, "--model", ckpt]
    sk = ["--skip-existing", *ARGS[:-2], "--mc", "1"]

    def chain_stores() -> None:
        # ---- the stores and the cache command ------------------------------------------------------------
        run("warm-up: predict --mc 2 (numba store filled)", [*P, "--out", W / "warm", *ARGS])
        run("cache list", ["cache"])
        run("cache list --store openvino", ["cache", "list", "--store", "openvino"])
        run("cache clear --store numba", ["cache", "clear", "--store", "numba"])
        run("cache clear twice (nothing left)", ["cache", "clear"])
        run("cache with an unknown action", ["cache", "purge"])
        run("cache --store bogus", ["cache", "list", "--store", "bogus"])
        run("limit env not a number", ["cache"], env={"AERIALMTL_CACHE_LIMIT_MB": "abc"})
        run("limit env negative", ["cache"], env={"AERIALMTL_CACHE_LIMIT_MB": "-5"})
        home_env = {"AERIALMTL_CACHE": None, "AERIALMTL_OPENVINO_CACHE": None, "XDG_CACHE_HOME": None}
        run("HOME empty: cache list", ["cache"], env={**home_env, "HOME": ""})
        run("HOME=/: cache list", ["cache"], env={**home_env, "HOME": "/"})
        run("XDG_CACHE_HOME relative: ignored", ["cache"], env={**home_env, "XDG_CACHE_HOME": "rel/dir"})
        run("XDG_CACHE_HOME=/: ignored", ["cache"], env={**home_env, "XDG_CACHE_HOME": "/"})
        f = W / "a-file"
        f.write_text("x")
        run("AERIALMTL_CACHE is a regular file: predict --mc 2", [*P, "--out", W / "p-cachefile", *ARGS],
            env={"AERIALMTL_CACHE": str(f), "AERIALMTL_OPENVINO_CACHE": str(f / "ov")})
        run("AERIALMTL_CACHE under /proc (unwritable): predict --mc 2", [*P, "--out", W / "p-proc", *ARGS],
            env={"AERIALMTL_CACHE": "/proc/aerialmtl", "AERIALMTL_OPENVINO_CACHE": "/proc/aerialmtl/ov"})

        def numba_case(name: str, damage: Callable[[Path], None]) -> None:
            cache = fresh(f"c-{name}")
            shutil.copytree(W / "cache-template" / "numba", cache / "numba", symlinks=True)
            damage(cache / "numba")
            run(f"numba store: {name}", [*P, "--out", W / f"p-{name}", *ARGS],
                env={"AERIALMTL_CACHE": str(cache), "AERIALMTL_OPENVINO_CACHE": str(cache / "ov")})

        template = fresh("cache-template")
        run("numba store template (fresh)", [*P, "--out", W / "p-template", *ARGS],
            env={"AERIALMTL_CACHE": str(template), "AERIALMTL_OPENVINO_CACHE": str(template / "ov")})

        def nbi(d: Path) -> Path:
            return sorted(d.glob("class_kernel_jit.kernel-*.nbi"))[0]

        def nbcs(d: Path) -> list[Path]:
            return sorted(d.glob("*.nbc"))

        def manifest_dir(d: Path) -> None:
            (d / "manifest").unlink()
            (d / "manifest").mkdir()

        def index_symlink(d: Path) -> None:
            p = nbi(d)
            p.unlink()
            p.symlink_to("/etc/passwd")

        def swap_data(d: Path) -> None:
            a, b = nbcs(d)[:2]
            da, db = a.read_bytes(), b.read_bytes()
            a.write_bytes(db)
            b.write_bytes(da)

        numba_case("manifest is a folder", manifest_dir)
        numba_case("index is a symlink to /etc/passwd", index_symlink)
        numba_case("two data files swapped", swap_data)
        numba_case("numba's staging file left by a kill",
                   lambda d: (d / (nbi(d).name + ".tmp.deadbeef")).write_bytes(b"half"))
        numba_case("an unrecorded extra index",
                   lambda d: (d / "class_kernel_jit.evil-1.py311.nbi").write_bytes(b"\x80"))
        numba_case("index truncated to 10 bytes", lambda d: nbi(d).write_bytes(nbi(d).read_bytes()[:10]))

        def store_is_file(d: Path) -> None:
            shutil.rmtree(d)
            d.write_text("not a folder")

        numba_case("the numba store is a regular file", store_is_file)

    def chain_openvino() -> None:
        # OpenVINO store
        ovc = fresh("ov-template")
        ov_env = {"AERIALMTL_CACHE": str(ovc), "AERIALMTL_OPENVINO_CACHE": str(ovc / "ov")}
        ovargs = ["--window", "64", "--overlap", "16", "--engine", "openvino", "--mc", "2"]
        run("openvino warm-up", [*P, "--out", W / "ov-warm", *ovargs], env=ov_env)

        def ov_case(name: str, damage: Callable[[Path], None], env: dict | None = None, prefix: list | None = None,
                    args: list | None = None) -> None:
            cache = fresh(f"ov-{name}")
            shutil.copytree(ovc / "ov", cache / "ov", symlinks=True)
            damage(cache / "ov")
            run(f"openvino store: {name}", [*P, "--out", W / f"ovp-{name}", *(args or ovargs)],
                env={"AERIALMTL_CACHE": str(cache), "AERIALMTL_OPENVINO_CACHE": str(cache / "ov"), **(env or {})},
                prefix=prefix)

        def blobs(d: Path) -> list[Path]:
            return sorted(d.rglob("*.blob"))

        ov_case("blobs emptied", lambda d: [b.write_bytes(b"") for b in blobs(d)])
        ov_case("record damaged", lambda d: [r.write_bytes(os.urandom(200)) for r in d.rglob("*.record")])

        def model_folder_is_file(d: Path) -> None:
            for sub in [p for p in d.iterdir() if p.is_dir() and p.name != "records"]:
                shutil.rmtree(sub)
                sub.write_text("x")

        ov_case("model folder replaced by a file", model_folder_is_file)

        def read_only(d: Path) -> None:
            for p in [d, *d.rglob("*")]:
                if p.is_dir():
                    os.chown(p, 65534, 65534)
                    p.chmod(0o555)

        ov_case("read-only store (no root override), blobs removed",
                lambda d: (read_only(d), [os.chmod(b.parent, 0o755) or b.unlink() or os.chmod(b.parent, 0o555)
                                          for b in blobs(d)]), prefix=NO_OVERRIDE)
        ov_case("entries are sockets", lambda d: [_socket_at(b) for b in blobs(d)])
        run("AERIALMTL_OPENVINO_CACHE empty: the store under AERIALMTL_CACHE",
            [*P, "--out", W / "ov-emptyenv", *ovargs], env={"AERIALMTL_OPENVINO_CACHE": ""})
        run("TMPDIR does not exist: cold openvino", [*P, "--out", W / "ov-tmpmissing", *ovargs],
            env={"TMPDIR": str(W / "no-such-tmp"), "AERIALMTL_CACHE": str(fresh("c-tmpmissing")),
                 "AERIALMTL_OPENVINO_CACHE": str(W / "c-tmpmissing" / "ov")})
        full = fresh("fulltmp")
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k,mode=1777", "tmpfs", str(full)],
                                 capture_output=True, check=False).returncode == 0
        if mounted:
            with open(full / "filler", "wb") as fh:
                try:
                    fh.write(b"\0" * 200_000)
                except OSError:
                    pass
            for engine in ("auto", "openvino"):
                c = fresh(f"c-full-{engine}")
                run(f"TMPDIR a full tmpfs, --engine {engine}, cold cache",
                    [*P, "--out", W / f"ov-full-{engine}", *ovargs[:4], "--engine", engine, "--mc", "2"],
                    env={"TMPDIR": str(full), "AERIALMTL_CACHE": str(c), "AERIALMTL_OPENVINO_CACHE": str(c / "ov")})
            subprocess.run(["umount", "-l", str(full)], check=False)
        run("limit 1 MiB: openvino predict evicts and still runs", [*P, "--out", W / "ov-evict", *ovargs],
            env={**ov_env, "AERIALMTL_CACHE_LIMIT_MB": "1"})
        run("limit 1 MiB: the next run rebuilds what was evicted", [*P, "--out", W / "ov-evict2", *ovargs],
            env={**ov_env, "AERIALMTL_CACHE_LIMIT_MB": "1"})

    def chain_sidecars() -> None:
        # ---- sidecars and --skip-existing ---------------------------------------------------------------------
        src = fresh("side")
        o2 = write_raster(src / "o.tif", rng.integers(1, 256, size=(3, 48, 64)).astype(np.uint8))
        S = ["predict", o2, "--model", ckpt, "--out", src / "p", *sk]
        run("sidecars: first run", S)
        run("sidecars: unchanged → skipped", S)
        (src / "o.prj").write_text('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
                                   'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]')
        run("sidecars: a .prj appears (internal CRS still wins)", S)
        (src / "o.prj").unlink()
        subprocess.run(["gdaladdo", "-ro", str(o2), "2"], capture_output=True, check=False)
        run("sidecars: external overviews .ovr appear", S)
        (src / "o.tif.aux.xml").write_text('<PAMDataset><PAMRasterBand band="1"><Metadata>'
                                           '<MDI key="STATISTICS_MEAN">5</MDI></Metadata></PAMRasterBand></PAMDataset>')
        run("sidecars: an .aux.xml with statistics only (as QGIS writes)", S)
        run("sidecars: same again → skipped", S)
        (src / "o.tif.msk").mkdir()
        run("sidecars: a folder named o.tif.msk", S)
        shutil.rmtree(src / "o.tif.msk")
        os.mkfifo(src / "o.wld")
        run("sidecars: a FIFO named o.wld (never opened)", S)
        (src / "o.wld").unlink()
        t0 = os.stat(o2).st_mtime_ns
        os.utime(o2, ns=(t0, t0 + 10**9))
        run("input touched (mtime only)", S)
        layer = src / "p" / "classes.tif"
        with open(layer, "r+b") as fh:
            fh.seek(layer.stat().st_size // 2)
            fh.write(bytes(4096))
        run("classes.tif with 4 KiB zeroed, same size", S)
        info_path = src / "p" / "prediction.json"

        def edit_info(change: Callable[[dict], None], name: str) -> None:
            info = json.loads(info_path.read_text())
            change(info)
            info_path.write_text(json.dumps(info))
            run(f"prediction.json edited: {name}", S)

        edit_info(lambda i: i["file_sha256"].update({"height.tif": "0" * 64}), "a wrong layer checksum")
        edit_info(lambda i: i.update(file_sha256=["x"]), "file_sha256 a list")
        edit_info(lambda i: i.update(provenance=None), "provenance null")
        edit_info(lambda i: i["provenance"].update(input="x"), "provenance.input a string")
        edit_info(lambda i: i["provenance"].update(settings="x"), "provenance.settings a string")
        (src / "p" / "height.tif").unlink()
        os.mkfifo(src / "p" / "height.tif")
        run("height.tif replaced by a FIFO", S)

    def chain_world() -> None:
        w = fresh("world")
        with rasterio.open(w / "o.tif", "w", driver="GTiff", width=64, height=48, count=3, dtype="uint8",
                           crs="EPSG:32631") as dst:
            dst.write(rng.integers(1, 256, size=(3, 48, 64)).astype(np.uint8))
        (w / "o.tfw").write_text("0.5\n0\n0\n-0.5\n500000.25\n5000000.25\n")
        WS = ["predict", w / "o.tif", "--model", ckpt, "--out", w / "p", *sk]
        run("world file: first run", WS)
        (w / "o.tfw").write_text("0.5\n0\n0\n-0.5\n600000.25\n5000000.25\n")
        run("world file moved 100 km east", WS)
        (w / "o.tfw").write_text("garbage\n")
        run("world file garbage", WS)
        (w / "o.tfw").unlink()
        run("world file removed", WS)
        v = fresh("vrt")
        write_raster(v / "a.tif", rng.integers(1, 256, size=(3, 48, 64)).astype(np.uint8))
        subprocess.run(["gdalbuildvrt", str(v / "m.vrt"), str(v / "a.tif")], capture_output=True, check=False)
        VS = ["predict", v / "m.vrt", "--model", ckpt, "--out", v / "p", *sk]
        run("VRT: first run", VS)
        (v / "a.tif.aux.xml").write_text('<PAMDataset><PAMRasterBand band="1"><NoDataValue>7</NoDataValue>'
                                         '</PAMRasterBand></PAMDataset>')
        run("VRT: its source gains an .aux.xml with nodata", VS)

    def chain_remote() -> None:
        # ---- remote inputs ------------------------------------------------------------------------------------
        www = fresh("www")
        write_raster(www / "o.tif", rng.integers(1, 255, (3, 1024, 1024)).astype(np.uint8), tiled=True,
                     blockxsize=256, blockysize=256)
        for limit in (2, 0):
            portfile = www.parent / f"port{limit}"
            portfile.unlink(missing_ok=True)
            srv = subprocess.Popen([sys.executable, str(ROOT / "tests" / "helpers" / "dying_server.py"), str(www),
                                    str(limit), str(portfile)])
            while not (portfile.exists() and portfile.read_text()):
                time.sleep(0.1)
            url = f"http://127.0.0.1:{portfile.read_text()}/o.tif"
            run(f"remote: server dies after {limit} range requests", ["predict", url, "--model", ckpt, "--out",
                                                                      W / f"r{limit}", *ARGS, "--mc", "1"],
                env={"GDAL_HTTP_MAX_RETRY": "0"})
            srv.kill()
            srv.wait()
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        run("remote: connection refused", ["predict", f"http://127.0.0.1:{port}/o.tif", "--model", ckpt, "--out",
                                           W / "rrefused", *ARGS])
        srv = subprocess.Popen([sys.executable, "-m", "http.server", "0", "--bind", "127.0.0.1", "--directory",
                                str(www)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        line = srv.stdout.readline() if srv.stdout else ""
        hport = line.split("port ")[-1].split(" ")[0] if "port" in line else "8000"
        run("remote: 404", ["predict", f"http://127.0.0.1:{hport}/missing.tif", "--model", ckpt, "--out", W / "r404",
                            *ARGS])
        run("remote: server ignores Range (200 with the whole file)", ["predict", f"http://127.0.0.1:{hport}/o.tif",
                                                                        "--model", ckpt, "--out", W / "rnorange",
                                                                        *ARGS, "--mc", "1"])
        srv.kill()
        srv.wait()

    def chain_schemas() -> None:
        # ---- schemas -----------------------------------------------------------------------------------------
        def edited_ckpt(name: str, edit: Callable[[dict], None]) -> Path:
            payload = torch.load(ckpt, weights_only=True)
            edit(payload)
            path = W / f"{name}.pt"
            torch.save(payload, path)
            return path

        for name, edit in [
            ("height_range strings", lambda p: p["meta"].update(height_range=["a", "b"])),
            ("gsd a string", lambda p: p["meta"].update(gsd="0.5")),
            ("calibration with decreasing heights", lambda p: p["meta"].update(calibration={
                "height_x": [0.0, 10.0], "height_y": [10.0, 0.0]})),
            ("calibration floors 1e30", lambda p: p["meta"].update(calibration={
                "height_x": [0.0, 10.0], "height_y": [0.0, 10.0], "std_floors": [1e30, 0.1], "std_edges": [5.0],
                "std_scales": [1.0, 1.0]})),
            ("an unknown meta key", lambda p: p["meta"].update(colour="red")),
            ("meta a list", lambda p: p.update(meta=[1, 2])),
        ]:
            run(f"checkpoint: {name}", ["predict", ortho, "--model", edited_ckpt(name.replace(" ", "_"), edit),
                                        "--out", W / f"ck-{name.replace(' ', '_')}", *ARGS])
        bad = fresh("badjson")
        (bad / "prediction.json").write_text("[]")
        run("buildings on a folder whose prediction.json is []", ["buildings", bad, "--out", W / "b.gpkg"])

    def chain_locks() -> None:
        # ---- locks ---------------------------------------------------------------------------------------------
        for name, owner, mode in (("own read-only", 0, 0o444), ("another user's", 65534, 0o644)):
            out = fresh(f"lock-{name.replace(' ', '_')}")
            out.chmod(0o1777)
            lock = out / ".aerialmtl.lock"
            lock.write_text('{"pid": 999999, "command": "predict"}')
            os.chown(lock, owner, owner)
            lock.chmod(mode)
            run(f"stale lock, {name}, run without root's overrides", [*P, "--out", out, *ARGS], prefix=NO_OVERRIDE)
        out = fresh("lock-fifo")
        os.mkfifo(out / ".aerialmtl.lock")
        run("lock file is a FIFO", [*P, "--out", out, *ARGS])
        out = fresh("lock-dir")
        (out / ".aerialmtl.lock").mkdir()
        run("lock file is a folder", [*P, "--out", out, *ARGS])

    def chain_qgis() -> None:
        # ---- the QGIS provider's command lines ---------------------------------------------------------------------
        q = fresh("qgis")
        shutil.copy(ortho, q / "-x.tif")
        shutil.copy(ortho, q / "--help")
        shutil.copy(ortho, q / "ortho with spaces é.tif")
        predict = ALGORITHMS["predict"]
        for name, value, out in (("input named -x.tif", "-x.tif", "p1"), ("input named --help", "--help", "p2"),
                                 ("input with spaces and é", "ortho with spaces é.tif", "p3"),
                                 ("output named -o", "-x.tif", "-o"), ("input named --version", "--version", "p4")):
            argv = command_line(["aerialmtl"], predict, {"INPUT": value, "MODEL": str(ckpt), "OUTPUT": out, "MC": 2,
                                                         "ENGINE": "torch", "WINDOW": 64, "OVERLAP": 16})
            run(f"QGIS provider: {name}", argv[1:], cwd=q)
        buildings = ALGORITHMS["buildings"]
        argv = command_line(["aerialmtl"], buildings, {"INPUT": "-p", "OUTPUT": "b.gpkg"})
        run("QGIS provider: buildings on a folder named -p (missing)", argv[1:], cwd=q)

    with ThreadPoolExecutor(max_workers=int(os.environ.get("HOSTILE_JOBS", "4"))) as pool:
        for fut in [pool.submit(c) for c in (chain_stores, chain_openvino, chain_sidecars, chain_world, chain_remote,
                                             chain_schemas, chain_locks, chain_qgis)]:
            fut.result()


def _socket_at(path: Path) -> None:
    path.unlink()
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(path))
    s.close()


if __name__ == "__main__":
    main()
