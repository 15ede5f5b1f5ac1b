"""Predicting a COG over HTTP against the same file on disk: time, requests and bytes transferred.

Serves a synthetic RGB COG from a local HTTP server on 127.0.0.1 that answers Range requests, predicts it
once from disk and once through its URL (``aerialmtl.io.paths`` GDAL settings), with a tiny untrained
D3-Net and T = 1 so that reading weighs as much as possible, and checks the maps are identical.

    python bench/remote_input.py --size 2048
"""

from __future__ import annotations

import argparse
import functools
import http.server
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.models import tiny_d3net  # noqa: E402

from aerialmtl.inference.predict import predict_raster  # noqa: E402

STATS = {"requests": 0, "bytes": 0}


class RangeHandler(http.server.SimpleHTTPRequestHandler):
    """Static files; ``Range: bytes=a-b`` → 206 with those bytes (counted in :data:`STATS`)."""

    def send_head(self):  # type: ignore[no-untyped-def]
        path = Path(self.translate_path(self.path))
        match = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        STATS["requests"] += 1
        if not path.is_file() or match is None:
            return super().send_head()
        size = path.stat().st_size
        start = int(match.group(1))
        end = min(int(match.group(2)) if match.group(2) else size - 1, size - 1)
        f = path.open("rb")
        f.seek(start)
        self.send_response(206)
        self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Content-Length", str(end - start + 1))
        self.end_headers()
        STATS["bytes"] += end - start + 1
        data = f.read(end - start + 1)
        f.close()
        self.wfile.write(data)
        return None

    def log_message(self, *args: object) -> None:
        pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--tile", type=int, default=512)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        rng = np.random.default_rng(0)
        img = rng.integers(0, 256, (3, args.size, args.size), dtype=np.uint8)
        profile = dict(driver="COG", width=args.size, height=args.size, count=3, dtype="uint8", crs="EPSG:32631",
                       transform=Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0), compress="DEFLATE", blocksize=512)
        with rasterio.open(root / "ortho.tif", "w", **profile) as dst:
            dst.write(img)
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(RangeHandler, directory=tmp))
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{httpd.server_address[1]}/ortho.tif"
        model = tiny_d3net()
        rows = []
        for label, src in (("local file", str(root / "ortho.tif")), ("HTTP (range requests)", url)):
            STATS.update(requests=0, bytes=0)
            t0 = time.perf_counter()
            predict_raster(src, model, root / label.split()[0], mc=1, window=args.tile, progress=False)
            rows.append((label, time.perf_counter() - t0, STATS["requests"], STATS["bytes"]))
        httpd.shutdown()
        with rasterio.open(root / "local" / "height.tif") as a, rasterio.open(root / "HTTP" / "height.tif") as b:
            same = bool(np.array_equal(a.read(), b.read()))
        size_mb = (root / "ortho.tif").stat().st_size / 2**20
    print(f"{args.size}² px RGB COG ({size_mb:.1f} MiB), tiny D3-Net, T=1, --tile {args.tile}; maps identical: {same}")
    print("| input | wall (s) | HTTP requests | bytes transferred |")
    print("|---|---|---|---|")
    for label, wall, n, nbytes in rows:
        print(f"| {label} | {wall:.1f} | {n if label != 'local file' else '-'} | "
              f"{f'{nbytes / 2**20:.1f} MiB' if label != 'local file' else '-'} |")


if __name__ == "__main__":
    main()
