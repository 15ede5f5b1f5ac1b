"""One Processing algorithm per aerialmtl command, built from its :class:`~.spec.Algorithm`.

``processAlgorithm`` turns the dialog's values into the command line (:func:`~.spec.command_line`), runs it
(:func:`~.runner.run_command`: progress bar, messages, Cancel → SIGTERM) and, when it succeeded, asks QGIS
to add the outputs when the run completes: a prediction's layers in a group named after its folder, each
with its ``.qml`` style and a readable name; the buildings file styled by height.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from processing.core.ProcessingConfig import ProcessingConfig
from qgis.core import (
    QgsClassificationQuantile,
    QgsFillSymbol,
    QgsGradientColorRamp,
    QgsGraduatedSymbolRenderer,
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingContext,
    QgsProcessingException,
    QgsProcessingLayerPostProcessorInterface,
    QgsProcessingOutputMultipleLayers,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
    QgsProcessingUtils,
    QgsProject,
    QgsRasterLayer,
    QgsVectorLayer,
)
from qgis.PyQt.QtGui import QColor

from .runner import Progress, run_command
from .spec import (
    EXECUTABLE_SETTING,
    PREDICTION_LAYERS,
    Algorithm,
    Param,
    Value,
    command_line,
    default_executable,
    dialog_message,
    not_found_message,
)

#: Output listing the layers a run added (prediction layers or the buildings file).
LAYERS_OUTPUT = "LAYERS"
#: Post-processors must outlive the algorithm object QGIS ran (it may be a copy deleted before the layers
#: are loaded), so they are kept here.
_POST_PROCESSORS: list[QgsProcessingLayerPostProcessorInterface] = []


class _IntoGroup(QgsProcessingLayerPostProcessorInterface):
    """Run by QGIS (main thread) after adding an output layer: style, name, place it in its group."""

    def __init__(self, group: str, name: str, position: int, style: str | None, height_field: str | None) -> None:
        super().__init__()
        self.group, self.name, self.position = group, name, position
        self.style, self.height_field = style, height_field

    def postProcessLayer(self, layer: Any, context: Any, feedback: Any) -> None:
        layer.setName(self.name)
        if self.style:
            _message, ok = layer.loadNamedStyle(self.style)
            if not ok:
                feedback.pushWarning(f"could not apply the style {self.style}: {_message}")
        elif self.height_field and layer.fields().indexOf(self.height_field) >= 0:
            _style_by_height(layer, self.height_field)
        layer.setCustomProperty("aerialmtl/position", self.position)
        layer.triggerRepaint()
        project = context.project() or QgsProject.instance()
        root = project.layerTreeRoot()
        node = root.findLayer(layer.id())
        if node is None or not self.group:
            return
        group = root.findGroup(self.group) or root.insertGroup(0, self.group)
        if node.parent() is group:
            return
        index = sum(1 for child in group.children() if _position(child) < self.position)
        group.insertChildNode(index, node.clone())
        node.parent().removeChildNode(node)


def _position(node: Any) -> int:
    """The place in its group of a layer tree node added by :class:`_IntoGroup` (0 for anything else)."""
    layer = node.layer() if hasattr(node, "layer") else None
    return int(layer.customProperty("aerialmtl/position", 0)) if layer is not None else 0


def _style_by_height(layer: Any, field: str) -> None:
    """Fill buildings by ``field`` (metres) in five quantile classes on a viridis ramp."""
    renderer = QgsGraduatedSymbolRenderer(field)
    renderer.setSourceSymbol(QgsFillSymbol.createSimple({"outline_color": "#232323", "outline_width": "0.2"}))
    renderer.setSourceColorRamp(QgsGradientColorRamp(QColor("#440154"), QColor("#fde725")))
    renderer.setClassificationMethod(QgsClassificationQuantile())
    renderer.updateClasses(layer, 5)
    layer.setRenderer(renderer)


class AerialMTLAlgorithm(QgsProcessingAlgorithm):
    """The Processing algorithm of one aerialmtl command (see :mod:`.spec`)."""

    def __init__(self, spec: Algorithm) -> None:
        super().__init__()
        self.spec = spec

    # ---- what QGIS shows ------------------------------------------------------------------------
    def createInstance(self) -> AerialMTLAlgorithm:
        return AerialMTLAlgorithm(self.spec)

    def name(self) -> str:
        return self.spec.command

    def displayName(self) -> str:
        return self.spec.label

    def shortHelpString(self) -> str:
        return (f"{self.spec.help}\n\nRuns `aerialmtl {self.spec.command}` (see `aerialmtl {self.spec.command} "
                "--help` for every option).")

    def initAlgorithm(self, config: Any = None) -> None:
        for p in self.spec.params:
            definition = _definition(p)
            if p.advanced:
                definition.setFlags(definition.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
            self.addParameter(definition)
        if self.spec.loads:
            self.addOutput(QgsProcessingOutputMultipleLayers(LAYERS_OUTPUT, "Layers added"))

    # ---- running ------------------------------------------------------------------------------------
    def processAlgorithm(self, parameters: dict[str, Any], context: Any, feedback: Any) -> dict[str, Any]:
        values = {p.name: self._value(p, parameters, context, feedback) for p in self.spec.params}
        executable = ProcessingConfig.getSetting(EXECUTABLE_SETTING) or default_executable()
        try:
            argv = command_line(str(executable), self.spec, values)
        except ValueError as exc:
            raise QgsProcessingException(str(exc)) from exc
        feedback.pushCommandInfo(" ".join(argv))
        stage = [""]

        def on_progress(p: Progress) -> None:
            if p.stage != stage[0]:
                stage[0] = p.stage
                feedback.setProgressText(f"{p.stage} ({p.unit})" if p.unit else p.stage)
            if p.percent is not None:
                feedback.setProgress(p.percent)

        def on_message(kind: str, text: str) -> None:
            if kind == "error":  # raised below as the run's error: QGIS shows it once, in the dialog's terms
                return
            if kind == "warning":
                feedback.pushWarning(dialog_message(self.spec, text))
            else:
                feedback.pushInfo(text)

        try:
            result = run_command(argv, on_progress, on_message, feedback.isCanceled)
        except OSError as exc:
            raise QgsProcessingException(not_found_message(str(executable), exc)) from exc
        if not result.ok:
            raise QgsProcessingException(dialog_message(self.spec, result.message()))
        outputs: dict[str, Any] = {p.name: values[p.name] for p in self.spec.params
                                   if p.kind in ("folder_out", "file_out")}
        if self.spec.loads == "prediction":
            outputs[LAYERS_OUTPUT] = self._load_prediction(str(values["OUTPUT"]), context)
        elif self.spec.loads == "vector":
            outputs[LAYERS_OUTPUT] = self._load_vector(str(values["OUTPUT"]), context)
        return outputs

    def _value(self, p: Param, parameters: dict[str, Any], context: Any, feedback: Any) -> Value:
        """The value of ``p`` as the command line takes it (``None``: not given)."""
        raw = parameters.get(p.name)
        missing = raw is None or raw == "" or (hasattr(raw, "isNull") and raw.isNull())
        if missing and p.default is not None:  # not given: the parameter's default (parameterAs* read it)
            missing = False
        if missing:
            if p.kind in ("folder_out", "file_out"):  # a destination left empty: a temporary one
                return str(self.parameterAsFileOutput(parameters, p.name, context)) or None
            return None if p.kind != "bool" else False
        if p.kind == "raster":
            layer = self.parameterAsRasterLayer(parameters, p.name, context)
            if layer is None:
                return str(self.parameterAsString(parameters, p.name, context)) or None
            if layer.providerType() != "gdal":
                raise QgsProcessingException(f"'{p.label}': layer '{layer.name()}' is not a raster GDAL reads "
                                             f"(provider {layer.providerType()}); save it as a GeoTIFF first")
            return str(layer.source())
        if p.kind == "vector":
            return str(self.parameterAsCompatibleSourceLayerPath(parameters, p.name, context, ["geojson"],
                                                                 "geojson", feedback))
        if p.kind in ("file", "folder"):
            return str(self.parameterAsFile(parameters, p.name, context)) or None
        if p.kind in ("folder_out", "file_out"):
            return str(self.parameterAsFileOutput(parameters, p.name, context)) or None
        if p.kind == "int":
            return int(self.parameterAsInt(parameters, p.name, context))
        if p.kind == "float":
            return float(self.parameterAsDouble(parameters, p.name, context))
        if p.kind == "enum":
            result: Value = p.choices[self.parameterAsEnum(parameters, p.name, context)]
            return result
        if p.kind == "bool":
            return bool(self.parameterAsBoolean(parameters, p.name, context))
        return str(self.parameterAsString(parameters, p.name, context)) or None

    # ---- outputs --------------------------------------------------------------------------------------
    def _load_on_completion(self, layer: Any, context: Any, name: str, group: str, position: int,
                            style: str | None, height_field: str | None = None) -> str:
        """Hand ``layer`` to QGIS to add to the project when the run completes (named, styled, grouped)."""
        context.temporaryLayerStore().addMapLayer(layer)
        hint = (QgsProcessingUtils.LayerHint.Raster if isinstance(layer, QgsRasterLayer)
                else QgsProcessingUtils.LayerHint.Vector)
        details = QgsProcessingContext.LayerDetails(name, context.project(), name, hint)
        post = _IntoGroup(group, name, position, style, height_field)
        _POST_PROCESSORS.append(post)
        details.setPostProcessor(post)
        context.addLayerToLoadOnCompletion(layer.id(), details)
        return str(layer.source())

    def _load_prediction(self, folder: str, context: Any) -> list[str]:
        """Add the layers of the prediction folder ``folder`` (one input) in a group named after it."""
        group = Path(folder).name
        added = []
        for position, (filename, name) in enumerate(PREDICTION_LAYERS):
            path = Path(folder) / filename
            if not path.is_file():
                continue
            layer = QgsRasterLayer(str(path), name, "gdal")
            if not layer.isValid():
                raise QgsProcessingException(f"QGIS cannot open {path}")
            style = path.with_suffix(".qml")
            added.append(self._load_on_completion(layer, context, name, group, position,
                                                  str(style) if style.is_file() else None))
        return added

    def _load_vector(self, path: str, context: Any) -> list[str]:
        """Add the vector file ``path`` (buildings), styled by height when it has ``height_m``."""
        if path.endswith(".city.json") or not os.path.isfile(path):
            return []
        name = f"buildings ({Path(path).stem})"
        layer = QgsVectorLayer(path, name, "ogr")
        if not layer.isValid():
            raise QgsProcessingException(f"QGIS cannot open {path}")
        return [self._load_on_completion(layer, context, name, "", 0, None, "height_m")]


def _definition(p: Param) -> Any:
    """The QGIS parameter of ``p``."""
    if p.kind == "raster":
        return QgsProcessingParameterRasterLayer(p.name, p.label, optional=p.optional)
    if p.kind == "vector":
        return QgsProcessingParameterFeatureSource(p.name, p.label, [QgsProcessing.TypeVectorPolygon],
                                                   optional=p.optional)
    if p.kind in ("file", "folder"):
        behavior = QgsProcessingParameterFile.Folder if p.kind == "folder" else QgsProcessingParameterFile.File
        return QgsProcessingParameterFile(p.name, p.label, behavior=behavior, extension=p.extension,
                                          optional=p.optional)
    if p.kind in ("int", "float"):
        number = QgsProcessingParameterNumber.Integer if p.kind == "int" else QgsProcessingParameterNumber.Double
        definition = QgsProcessingParameterNumber(p.name, p.label, type=number, defaultValue=p.default,
                                                  optional=p.optional)
        if p.minimum is not None:
            definition.setMinimum(p.minimum)
        return definition
    if p.kind == "enum":
        default = p.choices.index(str(p.default)) if p.default is not None else None
        return QgsProcessingParameterEnum(p.name, p.label, options=list(p.choices), defaultValue=default,
                                          optional=p.optional)
    if p.kind == "bool":
        return QgsProcessingParameterBoolean(p.name, p.label, defaultValue=bool(p.default))
    if p.kind == "folder_out":
        return QgsProcessingParameterFolderDestination(p.name, p.label)
    if p.kind == "file_out":
        filters = {"gpkg": "GeoPackage (*.gpkg);;GeoJSON (*.geojson);;CityJSON (*.city.json)",
                   "json": "JSON report (*.json)", "onnx": "ONNX (*.onnx);;OpenVINO IR (*.xml)"}
        return QgsProcessingParameterFileDestination(p.name, p.label, fileFilter=filters.get(p.extension, ""))
    return QgsProcessingParameterString(p.name, p.label, defaultValue=p.default, optional=p.optional)
