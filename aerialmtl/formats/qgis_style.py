"""QGIS layer styles (``.qml``) of the prediction layers and their mosaics.

QGIS applies ``<raster name without extension>.qml`` when it opens a raster (``height.tif`` →
``height.qml``, ``height.mosaic.vrt`` → ``height.mosaic.qml``), so every layer opens styled:

* ``height``: a ``singlebandpseudocolor`` renderer, an interpolated viridis ramp over 0..p98 metres
  (the 98th percentile of the layer, :func:`aerialmtl.io.stats.band_stats`, so that a few towers do
  not flatten the ramp; values above it take the top colour);
* ``height_std``, ``class_entropy``, ``class_mutual_info``: sequential ramps over 0..p98 of the layer
  (metres, nats); ``class_probabilities``: its first band over 0..1;
* ``unfamiliarity``: a sequential ramp over its fixed range 0..1 (0.5: as familiar as a typical training
  pixel; near 1: unlike anything the model was trained on);
* ``classes``: a ``paletted`` renderer with one entry per class, labelled with the class **name** and
  coloured as in the class scheme (QGIS 3.22 reads names neither from the colour table nor from tags).

Nodata is transparent twice over: QGIS uses the raster's nodata, and the renderer's
``rasterTransparency`` also lists the nodata value as 100 % transparent (in case a user switches the
source nodata off). The XML follows what QGIS ≥ 3.4 writes for these renderers (``rasterrenderer``
inside ``pipe``; ``colorrampshader`` items; ``colorPalette``/``paletteEntry``) and is built with
:mod:`xml.etree.ElementTree`.
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from aerialmtl.classes import ClassScheme
from aerialmtl.errors import OutputError
from aerialmtl.formats.prediction import (
    CLASS_ENTROPY,
    CLASS_MUTUAL_INFO,
    CLASS_PROBABILITIES,
    CLASS_SCHEME_TAG,
    CLASSES,
    HEIGHT,
    HEIGHT_STD,
    SHADOW,
    SHADOW_HEIGHT,
    UNFAMILIARITY,
    LayerSpec,
)
from aerialmtl.io.outputs import write_text
from aerialmtl.io.stats import BandStats, band_stats

#: The QGIS version written in the style (the oldest long-term release the styles are made for).
QGIS_VERSION = "3.22.0"


@dataclass(frozen=True)
class Ramp:
    """A colour ramp: hex colours at evenly spaced positions from the minimum to the maximum."""

    name: str
    colors: tuple[str, ...]


#: Perceptually uniform ramps (matplotlib's viridis and magma, ColorBrewer's YlOrRd), 5 stops each.
VIRIDIS = Ramp("viridis", ("#440154", "#3b528b", "#21918c", "#5ec962", "#fde725"))
MAGMA = Ramp("magma", ("#000004", "#51127c", "#b73779", "#fc8961", "#fcfdbf"))
YLORRD = Ramp("YlOrRd", ("#ffffb2", "#fecc5c", "#fd8d3c", "#f03b20", "#bd0026"))
BLUES = Ramp("Blues", ("#eff3ff", "#bdd7e7", "#6baed6", "#3182bd", "#08519c"))
#: Light (sunlit) to dark (shadow), ColorBrewer's Greys.
GREYS = Ramp("Greys", ("#f7f7f7", "#cccccc", "#969696", "#636363", "#252525"))

#: The ramp of each continuous layer.
RAMPS: dict[str, Ramp] = {HEIGHT: VIRIDIS, HEIGHT_STD: YLORRD, CLASS_ENTROPY: MAGMA, CLASS_MUTUAL_INFO: MAGMA,
                          CLASS_PROBABILITIES: BLUES, UNFAMILIARITY: MAGMA, SHADOW: GREYS, SHADOW_HEIGHT: VIRIDIS}
#: Layers styled over a fixed range (their values are shares, 0..1) instead of 0..p98.
FIXED_RANGES: dict[str, tuple[float, float]] = {CLASS_PROBABILITIES: (0.0, 1.0), UNFAMILIARITY: (0.0, 1.0),
                                                SHADOW: (0.0, 1.0)}

#: The top of the ramp when a layer has no valid pixel (nothing to scale to).
FALLBACK_MAX = 1.0


def _qgis_root() -> ET.Element:
    root = ET.Element("qgis", {"version": QGIS_VERSION, "styleCategories": "AllStyleCategories",
                               "hasScaleBasedVisibilityFlag": "0", "minScale": "1e+08", "maxScale": "0"})
    return root


def _pipe_tail(pipe: ET.Element, categorical: bool) -> None:
    ET.SubElement(pipe, "brightnesscontrast", {"brightness": "0", "contrast": "0", "gamma": "1"})
    ET.SubElement(pipe, "huesaturation", {"saturation": "0", "grayscaleMode": "0", "colorizeOn": "0",
                                          "colorizeRed": "255", "colorizeGreen": "128", "colorizeBlue": "128",
                                          "colorizeStrength": "100"})
    # zoomed out, average continuous values; classes stay classes (nearest)
    ET.SubElement(pipe, "rasterresampler", {"maxOversampling": "2"}
                  if categorical else {"maxOversampling": "2", "zoomedOutResampler": "bilinear"})
    ET.SubElement(pipe, "resamplingStage").text = "resamplingFilter"


def _transparency(renderer: ET.Element, nodata: float | int | None) -> None:
    tr = ET.SubElement(renderer, "rasterTransparency")
    if nodata is not None:
        values = ET.SubElement(tr, "singleValuePixelList")
        ET.SubElement(values, "pixelListEntry", {"min": _num(nodata), "max": _num(nodata),
                                                  "percentTransparent": "100"})


def _min_max_origin(renderer: ET.Element) -> None:
    """``limits`` None: the range written here is kept (QGIS does not recompute it from statistics)."""
    origin = ET.SubElement(renderer, "minMaxOrigin")
    for tag, text in (("limits", "None"), ("extent", "WholeRaster"), ("statAccuracy", "Estimated"),
                      ("cumulativeCutLower", "0.02"), ("cumulativeCutUpper", "0.98"), ("stdDevFactor", "2")):
        ET.SubElement(origin, tag).text = text


def _num(v: float | int) -> str:
    f = float(v)
    return str(int(f)) if f.is_integer() else repr(f)


def label_digits(span: float) -> int:
    """Decimals of the legend labels of a ramp over ``span``: 2, more for a small span (0.0004 m → 5)."""
    if not span > 0 or not math.isfinite(span):
        return 2
    return max(2, min(8, 2 - math.floor(math.log10(span / 4))))


def pseudocolor_style(vmin: float, vmax: float, ramp: Ramp, nodata: float | int | None, unit: str = "",
                      band: int = 1) -> ET.ElementTree:
    """A ``singlebandpseudocolor`` style: ``ramp`` interpolated from ``vmin`` to ``vmax`` (in ``unit``)."""
    if not vmax > vmin:
        vmax = vmin + FALLBACK_MAX
    root = _qgis_root()
    pipe = ET.SubElement(root, "pipe")
    renderer = ET.SubElement(pipe, "rasterrenderer", {
        "type": "singlebandpseudocolor", "band": str(band), "opacity": "1", "alphaBand": "-1",
        "classificationMin": _num(vmin), "classificationMax": _num(vmax), "nodataColor": "",
    })
    _transparency(renderer, nodata)
    _min_max_origin(renderer)
    digits = label_digits(vmax - vmin)
    shader = ET.SubElement(ET.SubElement(renderer, "rastershader"), "colorrampshader", {
        "colorRampType": "INTERPOLATED", "classificationMode": "1", "clip": "0",
        "minimumValue": _num(vmin), "maximumValue": _num(vmax), "labelPrecision": str(digits),
    })
    cramp = ET.SubElement(shader, "colorramp", {"type": "gradient", "name": "[source]"})
    stops = ":".join(f"{k / (len(ramp.colors) - 1):.4f};{_rgba(c)}" for k, c in enumerate(ramp.colors[1:-1], 1))
    for key, v in (("color1", _rgba(ramp.colors[0])), ("color2", _rgba(ramp.colors[-1])), ("discrete", "0"),
                   ("rampType", "gradient"), ("stops", stops)):
        ET.SubElement(cramp, "prop", {"k": key, "v": v})
    n = len(ramp.colors) - 1
    suffix = f" {unit}" if unit else ""
    for k, color in enumerate(ramp.colors):
        value = vmin + (vmax - vmin) * k / n
        ET.SubElement(shader, "item", {"alpha": "255", "value": repr(float(value)),
                                       "label": f"{value:.{digits}f}{suffix}", "color": color})
    _ramp_legend(shader, suffix, digits)
    _pipe_tail(pipe, categorical=False)
    ET.SubElement(root, "blendMode").text = "0"
    return ET.ElementTree(root)


def _ramp_legend(shader: ET.Element, suffix: str, digits: int) -> None:
    """The continuous legend QGIS (≥ 3.18) draws for an interpolated ramp, in the layers panel and in print
    layouts: its minimum and maximum labelled with the unit (``0 m`` … ``12.4 m``), ``digits`` decimals at most
    (trailing zeros dropped). Without it the legend shows the bare numbers.
    """
    settings = ET.SubElement(shader, "rampLegendSettings", {
        "minimumLabel": "", "maximumLabel": "", "prefix": "", "suffix": suffix, "direction": "0",
        "useContinuousLegend": "1", "orientation": "2"})
    options = ET.SubElement(ET.SubElement(settings, "numericFormat", {"id": "basic"}), "Option", {"type": "Map"})
    for name, value, kind in (("decimal_separator", "", "QChar"), ("decimals", str(digits), "int"),
                              ("rounding_type", "0", "int"), ("show_plus", "false", "bool"),
                              ("show_thousand_separator", "true", "bool"), ("show_trailing_zeros", "false", "bool"),
                              ("thousand_separator", "", "QChar")):
        ET.SubElement(options, "Option", {"name": name, "value": value, "type": kind})


def paletted_style(scheme: ClassScheme, nodata: float | int | None, band: int = 1) -> ET.ElementTree:
    """A ``paletted`` style: one entry per class index, labelled with its name, in the scheme's colour."""
    root = _qgis_root()
    pipe = ET.SubElement(root, "pipe")
    renderer = ET.SubElement(pipe, "rasterrenderer", {"type": "paletted", "band": str(band), "opacity": "1",
                                                      "alphaBand": "-1", "nodataColor": ""})
    _transparency(renderer, nodata)
    _min_max_origin(renderer)
    palette = ET.SubElement(renderer, "colorPalette")
    for index, (name, (r, g, b)) in enumerate(zip(scheme.names, scheme.colors, strict=True)):
        ET.SubElement(palette, "paletteEntry", {"value": str(index), "color": f"#{r:02x}{g:02x}{b:02x}",
                                                "alpha": "255", "label": name})
    _pipe_tail(pipe, categorical=True)
    ET.SubElement(root, "blendMode").text = "0"
    return ET.ElementTree(root)


def _rgba(hex_color: str) -> str:
    h = hex_color.lstrip("#")
    return f"{int(h[0:2], 16)},{int(h[2:4], 16)},{int(h[4:6], 16)},255"


def class_scheme_of(spec: LayerSpec) -> ClassScheme | None:
    """The class scheme carried by a ``classes`` layer spec (its :data:`CLASS_SCHEME_TAG` tag)."""
    text = spec.tags.get(CLASS_SCHEME_TAG)
    return ClassScheme.from_dict(json.loads(text)) if text else None


def layer_style(spec: LayerSpec, stats: BandStats | None) -> ET.ElementTree:
    """The style of a prediction layer (or of its mosaic).

    Args:
        spec: the layer (name, nodata, unit, class scheme in its tags).
        stats: statistics of band 1 of the written raster (the ramp ends at their ``p98``); ``None``
            when no pixel is valid.
    """
    if spec.name == CLASSES:
        scheme = class_scheme_of(spec)
        if scheme is None:
            raise OutputError(f"layer '{spec.name}' carries no class scheme; cannot style it with class names")
        return paletted_style(scheme, spec.nodata)
    if spec.name in FIXED_RANGES:
        return pseudocolor_style(*FIXED_RANGES[spec.name], RAMPS[spec.name], spec.nodata)
    vmax = stats.p98 if stats is not None else FALLBACK_MAX
    unit = spec.units[0] if spec.units else ""
    return pseudocolor_style(0.0, max(vmax, 0.0), RAMPS.get(spec.name, VIRIDIS), spec.nodata, unit)


def write_style(path: str | Path, tree: ET.ElementTree, atomic: bool = True) -> Path:
    """Write a style as QGIS does (its DOCTYPE line, UTF-8); ``path`` is replaced atomically unless
    ``atomic`` is false (``path`` is then itself a staging file that the caller renames).
    """
    path = Path(path)
    ET.indent(tree, space="  ")
    root = tree.getroot()
    assert root is not None
    text = "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + ET.tostring(root, encoding="unicode") + "\n"
    return write_text(path, text, "a QGIS style", atomic)


def style_path(raster: str | Path) -> Path:
    """Where QGIS looks for the style of ``raster``: its path with ``.qml`` for its last extension."""
    return Path(raster).with_suffix(".qml")


def write_raster_style(raster: str | Path, spec: LayerSpec) -> Path:
    """Write the style of layer ``spec`` beside ``raster`` (a layer or a VRT mosaic of it).

    The ramp's range comes from the raster's overviews (:func:`aerialmtl.io.stats.band_stats`).
    """
    stats = None if spec.categorical else band_stats(raster)
    return write_style(style_path(raster), layer_style(spec, stats))


__all__ = ["BLUES", "FIXED_RANGES", "MAGMA", "QGIS_VERSION", "RAMPS", "VIRIDIS", "YLORRD", "Ramp", "class_scheme_of",
           "layer_style", "paletted_style", "pseudocolor_style", "style_path", "write_raster_style", "write_style"]
