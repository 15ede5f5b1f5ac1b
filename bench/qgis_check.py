"""Open a prediction run in QGIS (headless) and report what a user would see: does every layer come up styled?

Two steps, two interpreters (QGIS' Python bindings live in the system Python, aerialmtl in yours):

    python bench/qgis_check.py make /tmp/qgis_run          # aerialmtl: two inputs, mosaics, buildings
    QT_QPA_PLATFORM=offscreen /usr/bin/python3 bench/qgis_check.py check /tmp/qgis_run

``check`` needs only PyQGIS and GDAL's Python bindings (Debian: ``apt install python3-qgis``; QGIS 3.22
LTR with GDAL 3.6 in Debian 12). For every ``.tif`` and ``.mosaic.vrt`` it opens a ``QgsRasterLayer``
(which applies the ``.qml`` of the same name, as QGIS does when a file is dropped on the map), prints the
renderer type, its range or class labels, the legend entries and the overviews GDAL reports; for every
GeoPackage it prints the warnings GDAL emits when opening it. It renders each styled layer to a PNG and
checks that the nodata corner is transparent. Exit status 1 when any check fails.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any


def make(root: Path) -> None:
    import numpy as np
    import rasterio
    from affine import Affine

    from aerialmtl.buildings import write_buildings
    from aerialmtl.classes import ClassScheme
    from aerialmtl.formats.checkpoint import ModelMeta
    from aerialmtl.inference.jobs import predict_many
    from aerialmtl.models.config import ModelConfig
    from aerialmtl.models.d3net import D3Net

    root.mkdir(parents=True, exist_ok=True)
    scheme = ClassScheme.load("synthetic")
    cfg = ModelConfig(num_classes=scheme.num_classes, growth_rate=4, block_config=(1, 1, 1, 1), num_init_features=8,
                      bn_size=2)
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0,) * 3, (40.0,) * 3, 0.5, ("r", "g", "b"))
    model = D3Net(meta.model)
    rng = np.random.default_rng(0)
    orthos = []
    for k in range(2):
        img = rng.integers(1, 256, (3, 768, 768)).astype(np.uint8)
        img[:, :32, :32] = 0  # nodata corner
        path = root / f"ortho{k}.tif"
        with rasterio.open(path, "w", driver="GTiff", width=768, height=768, count=3, dtype="uint8",
                           crs="EPSG:32631", transform=Affine(0.5, 0, 500000.0 + 300 * k, 0, -0.5, 5000000.0),
                           nodata=0) as dst:
            dst.write(img)
        orthos.append(path)
    predict_many(orthos, (model, meta), root / "out", mc=3, window=128, overlap=32, progress=False, overwrite=True)
    # the untrained model may find no building: draw some into the first folder's classes for the footprints
    cls_path = root / "out" / "ortho0" / "classes.tif"
    with rasterio.open(cls_path) as src:
        profile, cls = src.profile, src.read(1)
    cls[100:140, 200:256] = scheme.names.index("building")
    b_pred = root / "buildings_pred"
    b_pred.mkdir(exist_ok=True)
    for name in ("height.tif", "height_std.tif", "class_entropy.tif"):
        (b_pred / name).write_bytes((root / "out" / "ortho0" / name).read_bytes())
    with rasterio.open(b_pred / "classes.tif", "w", **{**profile, "driver": "GTiff"}) as dst:
        dst.write(cls, 1)
        with rasterio.open(cls_path) as src:
            dst.update_tags(**src.tags())
    write_buildings(b_pred, [root / "buildings.gpkg"], overwrite=True)
    print(f"wrote {root}")


def check(root: Path) -> int:
    from osgeo import gdal
    from qgis.core import (
        QgsApplication,
        QgsMapRendererParallelJob,
        QgsMapSettings,
        QgsRasterLayer,
        QgsVectorLayer,
    )
    from qgis.PyQt.QtCore import QSize
    from qgis.PyQt.QtGui import QColor

    app = QgsApplication([], False)
    app.initQgis()
    failures = 0
    print(f"QGIS {__import__('qgis.core', fromlist=['Qgis']).Qgis.QGIS_VERSION}, GDAL {gdal.__version__}")
    rasters = sorted((root / "out").glob("*/*.tif")) + sorted((root / "out").glob("*.mosaic.vrt"))
    for path in rasters:
        layer = QgsRasterLayer(str(path), path.name)
        r: Any = layer.renderer()
        kind = r.type() if r else None
        qml = path.with_suffix(".qml").is_file()
        if kind == "paletted":
            detail = "classes " + ", ".join(f"{c.value}={c.label}" for c in r.classes())
        elif kind == "singlebandpseudocolor":
            shader = r.shader().rasterShaderFunction()
            detail = f"range {shader.minimumValue():.3g}..{shader.maximumValue():.3g}"
        else:
            detail = ""
        legend = [label for label, _ in layer.legendSymbologyItems()]  # what the Layers panel lists
        ds = gdal.Open(str(path))
        ovs = ds.GetRasterBand(1).GetOverviewCount()
        # render the whole layer; the upper-left corner of the first input is nodata → transparent
        settings = QgsMapSettings()
        settings.setLayers([layer])
        settings.setExtent(layer.extent())
        settings.setOutputSize(QSize(128, 128))
        settings.setBackgroundColor(QColor(0, 0, 0, 0))
        job = QgsMapRendererParallelJob(settings)
        job.start()
        job.waitForFinished()
        img = job.renderedImage()
        corner_alpha = img.pixelColor(2, 2).alpha()  # every input has a nodata upper-left corner
        centre_alpha = img.pixelColor(64, 64).alpha()
        expected = "paletted" if path.name.startswith("classes") else "singlebandpseudocolor"
        ok = qml and kind == expected and corner_alpha == 0 and centre_alpha == 255
        if path.name.startswith("classes"):
            ok = ok and "building" in " ".join(legend).lower() and not any(s.isdigit() for s in legend)
        failures += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {path.relative_to(root)}: renderer {kind}, {detail}; legend {legend[:6]}"
              f"{'...' if len(legend) > 6 else ''}; GDAL overviews {ovs}; nodata corner alpha {corner_alpha}")
    for gpkg in sorted(root.glob("*.gpkg")):
        messages: list[str] = []
        gdal.PushErrorHandler(lambda cls, no, msg, out=messages: out.append(msg))
        ds = gdal.OpenEx(str(gpkg))
        gdal.PopErrorHandler()
        vl = QgsVectorLayer(str(gpkg), gpkg.name, "ogr")
        ok = ds is not None and not messages and vl.isValid()
        failures += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {gpkg.name}: GDAL {gdal.__version__} messages {messages or 'none'}; "
              f"QGIS features {vl.featureCount()}")
    return 1 if failures else 0


if __name__ == "__main__":
    cmd, where = sys.argv[1], Path(sys.argv[2])
    if cmd == "make":
        make(where)
    else:
        code = check(where)
        sys.stdout.flush()
        os._exit(code)  # QgsApplication.exitQgis() of a headless app may abort in its teardown
