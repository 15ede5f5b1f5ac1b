"""What ownership, locks and verified completeness cost (issue 18): ``python -m experiments.output_folder_cost.run``.

Measures, on this machine:

* the checkpoint fingerprint (SHA-256 of the file) of the default D3-Net (DenseNet-121 encoder), which
  every ``predict --skip-existing`` computes once per run;
* :meth:`PredictionFolder.check` of a finished prediction folder (parse ``prediction.json``, compare
  sizes, open every layer, compare provenance), done once per input by ``--skip-existing``;
* taking and releasing an output folder's lock (every command, once per run).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _best(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=2048, help="side of the prediction folder's layers (px)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    import rasterio
    from affine import Affine

    from aerialmtl.classes import ClassScheme
    from aerialmtl.formats.checkpoint import ModelMeta, bytes_fingerprint, save_checkpoint
    from aerialmtl.formats.prediction import INFO_FILE, PredictionFolder
    from aerialmtl.io.outputs import FolderLock
    from aerialmtl.models.config import ModelConfig
    from aerialmtl.models.d3net import D3Net

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        scheme = ClassScheme.load("synthetic")
        cfg = ModelConfig(num_classes=scheme.num_classes)
        meta = ModelMeta(model=cfg, classes=scheme, bands=(1, 2, 3), mean=(0.0,) * 3, std=(1.0,) * 3, gsd=0.5)
        ckpt = root / "best.pt"
        save_checkpoint(ckpt, D3Net(cfg), meta)
        mib = ckpt.stat().st_size / 2**20
        t_fp = _best(lambda: bytes_fingerprint(ckpt.read_bytes()), args.repeat)  # what predict hashes once loaded
        print(f"checkpoint fingerprint: {mib:.1f} MiB in {t_fp:.3f} s ({mib / t_fp:.0f} MiB/s)")

        pred = root / "pred"
        pred.mkdir()
        n = args.size
        files, sizes = {}, {}
        for name, dtype in (("height", "float32"), ("height_std", "float32"), ("classes", "uint8"),
                            ("class_entropy", "float32"), ("class_mutual_info", "float32")):
            path = pred / f"{name}.tif"
            with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype=dtype, crs="EPSG:32631",
                               transform=Affine(0.5, 0, 500000, 0, -0.5, 5000000), tiled=True,
                               compress="deflate") as dst:
                dst.write(np.zeros((1, n, n), dtype))
            files[name], sizes[path.name] = path.name, path.stat().st_size
        prov = {"checkpoint": "sha256:x", "settings": {"mc_samples": 30}, "input": {"path": "o.tif"}}
        (pred / INFO_FILE).write_text(json.dumps({"files": files, "file_sizes": sizes, "provenance": prov,
                                                  "grid": {"width": n, "height": n}}))
        folder = PredictionFolder(pred)
        assert folder.check(prov) is None
        t_check = _best(lambda: folder.check(prov), args.repeat)
        print(f"PredictionFolder.check: 5 layers of {n}x{n} px in {t_check * 1e3:.1f} ms")

        def lock() -> None:
            with FolderLock(pred, "bench"):
                pass

        t_lock = _best(lock, max(args.repeat, 20))
        print(f"FolderLock acquire + release: {t_lock * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
