"""Headless QGIS check of the Processing plugin (run by tests/test_qgis_plugin.py with QGIS's own Python).

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 tests/qgis_headless.py PLUGIN_ZIP AERIALMTL MODEL ORTHO BIG_ORTHO WORK

Installs the plugin from its zip into a fresh plugin folder, registers the provider as QGIS does, then runs
through ``processing.run`` and loads the results as the toolbox does (``handleAlgorithmResults``):

1. ``aerialmtl:predict`` with T = 4 on ORTHO within a memory-layer AOI (its left half), 2.
``aerialmtl:buildings`` on that prediction, 3. ``aerialmtl:evaluate`` of it against ``ndsm.tif`` beside
ORTHO, 4. ``aerialmtl:export`` of the model's height task to ONNX, 5. ``aerialmtl:tile`` of ORTHO with
that nDSM, 6. predict with a missing model (an error), 7. predict on BIG_ORTHO, canceled at the first
progress step.

Prints one JSON object (versions, progress seen, the layers in the project with their validity, name,
group and renderer, what the canceled run left) on stdout; the pytest side asserts on it. Needs no
aerialmtl in this Python: the plugin runs the AERIALMTL program.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

from qgis.core import (  # noqa: E402 - after the platform is chosen
    Qgis,
    QgsApplication,
    QgsLayerTreeGroup,
    QgsProcessingContext,
    QgsProcessingException,
    QgsProcessingFeedback,
    QgsProject,
)


class Recorder(QgsProcessingFeedback):  # type: ignore[misc]
    """Feedback that records progress and messages, and can press Cancel at the first progress step."""

    def __init__(self, cancel_at_first_step: bool = False) -> None:
        super().__init__()
        self.progress: list[float] = []
        self.errors: list[str] = []
        self.warnings: list[str] = []
        self.cancel_at_first_step = cancel_at_first_step
        self.canceled_at: float | None = None
        self.progressChanged.connect(self._progress)

    def _progress(self, value: float) -> None:
        self.progress.append(float(value))
        if self.cancel_at_first_step and 0 < value < 100 and self.canceled_at is None:
            self.canceled_at = value
            self.cancel()

    def pushWarning(self, warning: str) -> None:  # noqa: N802 - QGIS's name
        self.warnings.append(warning)
        super().pushWarning(warning)

    def reportError(self, error: str, fatalError: bool = False) -> None:  # noqa: N802, N803 - QGIS's names
        self.errors.append(error)
        super().reportError(error, fatalError)


def _renderer(layer: Any) -> dict[str, Any]:
    r = layer.renderer()
    info: dict[str, Any] = {"type": r.type() if r is not None else None}
    if r is not None and r.type() == "paletted":
        info["classes"] = [c.label for c in r.classes()]
    if r is not None and r.type() == "singlebandpseudocolor":
        shader = r.shader().rasterShaderFunction()
        items = shader.colorRampItemList()
        info["min"], info["max"], info["colors"] = shader.minimumValue(), shader.maximumValue(), len(items)
        legend = shader.legendSettings()  # the continuous legend of the layers panel and print layouts
        info["legend_suffix"] = legend.suffix() if legend is not None else None
    if r is not None and r.type() == "graduatedSymbol":
        info["field"], info["ranges"] = r.classAttribute(), len(r.ranges())
    return info


def _layers() -> list[dict[str, Any]]:
    root = QgsProject.instance().layerTreeRoot()
    out = []
    for node in root.findLayers():
        layer = node.layer()
        parent = node.parent()
        out.append({
            "name": layer.name(), "valid": layer.isValid(), "source": layer.source(),
            "group": parent.name() if isinstance(parent, QgsLayerTreeGroup) and parent is not root else "",
            "features": layer.featureCount() if hasattr(layer, "featureCount") else None,
            "renderer": _renderer(layer),
        })
    return out


def _run(algorithm: str, params: dict[str, Any], feedback: Recorder) -> dict[str, Any]:
    """Run like the toolbox: the algorithm, then loading its results into the project."""
    import processing
    from processing.gui.Postprocessing import handleAlgorithmResults

    alg = QgsApplication.processingRegistry().createAlgorithmById(algorithm)
    context = QgsProcessingContext()
    context.setProject(QgsProject.instance())
    start = time.perf_counter()
    try:
        results = processing.run(alg, params, feedback=feedback, context=context)
    except QgsProcessingException as exc:
        return {"error": str(exc), "seconds": time.perf_counter() - start, "progress": feedback.progress,
                "errors": feedback.errors, "warnings": feedback.warnings}
    progress = list(feedback.progress)  # before loading, which sets the bar to 100 itself
    handleAlgorithmResults(alg, context, QgsProcessingFeedback(), showResults=False)
    return {"results": {k: v for k, v in results.items() if isinstance(v, (str, list))},
            "seconds": time.perf_counter() - start, "progress": progress, "errors": feedback.errors,
            "warnings": feedback.warnings}


def _left_half(raster: str) -> Any:
    """A memory polygon layer over the left half of ``raster`` (QGIS converts it to GeoJSON for the CLI)."""
    from qgis.core import QgsFeature, QgsGeometry, QgsRasterLayer, QgsRectangle, QgsVectorLayer

    source = QgsRasterLayer(raster, "ortho", "gdal")
    extent = source.extent()
    half = QgsRectangle(extent.xMinimum(), extent.yMinimum(), extent.center().x(), extent.yMaximum())
    layer = QgsVectorLayer(f"Polygon?crs={source.crs().authid()}", "aoi", "memory")
    feature = QgsFeature()
    feature.setGeometry(QgsGeometry.fromRect(half))
    layer.dataProvider().addFeatures([feature])
    layer.updateExtents()
    return layer


def main(plugin_zip: str, program: str, model: str, ortho: str, big_ortho: str, work: str) -> dict[str, Any]:
    from osgeo import gdal

    QgsApplication.setPrefixPath("/usr", True)
    app = QgsApplication([], False)
    app.initQgis()
    sys.path.append(os.path.join(QgsApplication.prefixPath(), "share", "qgis", "python", "plugins"))
    from processing.core.Processing import Processing
    from processing.core.ProcessingConfig import ProcessingConfig

    Processing.initialize()
    plugins = Path(tempfile.mkdtemp(prefix="qgis-plugins-"))
    with zipfile.ZipFile(plugin_zip) as zf:  # "Install from ZIP"
        zf.extractall(plugins)
    sys.path.insert(0, str(plugins))
    import aerialmtl_processing

    plugin = aerialmtl_processing.classFactory(None)
    plugin.initProcessing()
    from aerialmtl_processing.spec import EXECUTABLE_SETTING

    ProcessingConfig.setSettingValue(EXECUTABLE_SETTING, program)
    report: dict[str, Any] = {
        "qgis": Qgis.QGIS_VERSION, "gdal": gdal.__version__, "python": sys.version.split()[0],
        "algorithms": sorted(a.id() for a in QgsApplication.processingRegistry().providerById("aerialmtl")
                             .algorithms()),
    }
    work_dir = Path(work)
    pred = work_dir / "pred"
    report["predict"] = _run("aerialmtl:predict", {
        "INPUT": ortho, "MODEL": model, "MC": 4, "WINDOW": 64, "OVERLAP": 16, "AOI": _left_half(ortho),
        "OUTPUT": str(pred)}, Recorder())
    report["buildings"] = _run("aerialmtl:buildings", {
        "INPUT": str(pred), "MIN_AREA": 1.0, "OUTPUT": str(work_dir / "buildings.gpkg")}, Recorder())
    report["evaluate"] = _run("aerialmtl:evaluate", {
        "PRED": str(pred), "HEIGHT": str(Path(ortho).with_name("ndsm.tif")), "NO_PLOTS": True,
        "OUTPUT": str(work_dir / "report.json")}, Recorder())
    report["export"] = _run("aerialmtl:export", {
        "INPUT": model, "TASK": 1, "OUTPUT": str(work_dir / "height.onnx")}, Recorder())  # enum index 1: height
    report["tile"] = _run("aerialmtl:tile", {
        "ORTHO": ortho, "NDSM": str(Path(ortho).with_name("ndsm.tif")), "SIZE": 32,
        "OUTPUT": str(work_dir / "tiles")}, Recorder())
    report["failing"] = _run("aerialmtl:predict", {  # an error: the command's one line
        "INPUT": ortho, "MODEL": str(work_dir / "missing.pt"), "OUTPUT": str(work_dir / "failed")}, Recorder())
    canceled = work_dir / "canceled"
    feedback = Recorder(cancel_at_first_step=True)
    report["cancel"] = _run("aerialmtl:predict", {
        "INPUT": big_ortho, "MODEL": model, "MC": 8, "WINDOW": 64, "OVERLAP": 16, "OUTPUT": str(canceled)}, feedback)
    report["cancel"]["canceled_at"] = feedback.canceled_at
    report["cancel"]["left"] = sorted(p.name for p in canceled.iterdir()) if canceled.exists() else None
    report["layers"] = _layers()
    plugin.unload()
    app.exitQgis()
    return report


if __name__ == "__main__":
    print(json.dumps(main(*sys.argv[1:7])))
