"""MkDocs hooks of the documentation site (``hooks:`` in mkdocs.yml): what the site must never show.

* The command-line reference (mkdocs-click) prints ``option.default``; click 8.3+ keeps ``UNSET`` there for
  an option declared without a default, which the table showed as ``Sentinel.UNSET``.
  :func:`use_real_defaults` makes the table show what click itself uses (``False`` for a flag, ``None`` for
  an option that is simply not passed). tests/test_docs.py renders the page through the same function.
* A page that shows a warning, a traceback, ``Sentinel`` or a path of the machine that built the site fails
  the build (:func:`problems`): the notebook pages are run at build time, and a cell that prints a warning
  (a stderr output block) or the build's temporary folder would otherwise be published as it is.
* The pictures of what the package makes (:func:`site_figures`) are made by the build, not pasted: a reduced
  demo (a synthetic town, the demo's pipeline with a smaller town and fewer steps) and the small-area recipe
  on the sample area ``samples/autzen_west`` with a short training; the pages show them from
  :data:`FIGURES_DIR`. They cost about a minute or two on 2 CPU cores (the build prints each stage's time).
* The notebook's kernel inherits :data:`NOTEBOOK_WARNINGS` (``PYTHONWARNINGS``, set by :func:`on_config`):
  the one warning a barely trained model may give on the page ("no building pixel", when it found no
  building) is left out there, so that the notebook's cells need no warning-capture code; any other
  warning still fails the build.
"""

from __future__ import annotations

import copy
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent


# ---- the CLI reference's defaults ---------------------------------------------------------------
def real_default(option: Any) -> Any:
    """The default click uses for ``option`` (``None`` for an option without one, ``False`` for a flag)."""
    import click

    default = option.default
    if default is None or not _is_unset(default):
        return default
    if getattr(option, "is_flag", False) and not getattr(option, "multiple", False):
        value = option.get_default(click.Context(click.Command("docs")), call=False)
        return None if _is_unset(value) else value
    return None


def _is_unset(value: Any) -> bool:
    """Whether ``value`` is click's marker for "no default given" (click 8.3+)."""
    return type(value).__name__ == "Sentinel" or repr(value).startswith("Sentinel.")


def use_real_defaults() -> None:
    """Make mkdocs-click's option tables show :func:`real_default` (idempotent)."""
    from mkdocs_click import _docs

    original = _docs._format_table_option_row
    if getattr(original, "real_defaults", False):
        return

    def row(option: Any) -> str:
        shown = copy.copy(option)
        shown.default = real_default(option)
        return str(original(shown))

    row.real_defaults = True  # type: ignore[attr-defined]
    _docs._format_table_option_row = row


# ---- what no page may show ---------------------------------------------------------------------
#: A notebook cell's stderr output (a warning, a progress bar) as nbconvert renders it.
STDERR_BLOCK = re.compile(r'<[^>]*(data-mime-type="application/vnd\.jupyter\.stderr"|class="[^"]*output_stderr)')
#: Names of folders made by :mod:`tempfile` (``tmpab12cd34``), pytest and the uncertainty notebook.
TEMP_NAMES = r"(?:tmp[a-z0-9_]{8}|pytest-of-|aerialmtl_nb_|aerialmtl_docs_)"


def machine_paths() -> list[str]:
    """Absolute paths of this machine that a page must not show: the checkout, Python's prefix and the home
    folder, each with a trailing separator.
    """
    paths = {str(REPO), sys.prefix, sys.base_prefix, os.path.expanduser("~")}
    return sorted({p.rstrip(os.sep) + os.sep for p in paths if len(p.strip(os.sep)) > 0})


def temporary_paths(html: str) -> list[str]:
    """Folders the build made in the temporary folder that ``html`` shows (``/tmp/aerialmtl_nb_x1y2``); a
    command in prose (``aerialmtl demo /tmp/demo3``) is not one.
    """
    tmp = re.escape(tempfile.gettempdir().rstrip(os.sep) + os.sep)
    return sorted(set(re.findall(tmp + TEMP_NAMES + r"[\w.-]*", html)))


def problems(html: str) -> list[str]:
    """What is wrong with a built page's HTML: warning blocks, tracebacks, ``Sentinel``, this machine's paths."""
    found = []
    if STDERR_BLOCK.search(html):
        found.append("a cell's stderr output (a warning or a progress bar)")
    for word in ("Traceback", "Sentinel"):
        if word in html:
            found.append(f"'{word}'")
    for path in machine_paths() + temporary_paths(html):
        if path in html:
            found.append(f"the path {path} of the machine that built the site")
    return found


# ---- the pictures of what the package makes ----------------------------------------------------------
#: Site folder of the figures the build makes (pages link ``images/built/NAME.png``).
FIGURES_DIR = "images/built"
#: The synthetic towns of the site's pictures: the demo's pipeline and network (``aerialmtl demo``), smaller
#: towns (pixels of 0.25 m) and a short training, validated once at its end.
DOCS_TOWN = {"train_size": 384, "test_size": 256, "patch": 64, "stride": 32, "steps": 200, "mc": 8}
#: The small-area recipe on samples/autzen_west, shortened for the site: patches, stride, steps, MC samples.
DOCS_AREA = {"size": 64, "stride": 32, "steps": 200, "mc": 8}
#: The figures :func:`site_figures` makes.
FIGURE_NAMES = ("demo_maps.png", "demo_overview.png", "qgis_layers.png", "area_maps.png",
                "area_height_reliability.png", "area_sparsification.png")
#: A folder to keep the figures in between builds (``mkdocs serve`` while writing, a second build): when it
#: holds all of :data:`FIGURE_NAMES` they are read from it instead of made again. Unset: made every build.
FIGURES_CACHE_ENV = "AERIALMTL_DOCS_FIGURES"
#: ``PYTHONWARNINGS`` of the notebook's kernel (see the module docstring).
NOTEBOOK_WARNINGS = "ignore:no building pixel in:UserWarning"
SAMPLE = REPO / "samples" / "autzen_west"
_FIGURES: dict[str, bytes] = {}
#: What the build's runs measured, for the figures' titles and the build's log.
RUN_NOTES: dict[str, str] = {}


def _png(fig: Any, dpi: float) -> bytes:
    """``fig`` as PNG bytes (closed afterwards)."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)
    return buf.getvalue()


def products_figure(pred_dir: Path, ortho: Path, title: str, crop_to_valid: bool = False) -> Any:
    """One row: the orthophoto, predicted height, its spread, the classes (if predicted) and the unfamiliarity,
    each in the colours of the QGIS style ``predict`` writes beside it, with its unit.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import rasterio
    from rasterio.enums import Resampling

    from aerialmtl.evaluation.maps import layer_cmap, load_prediction_maps
    from aerialmtl.formats.prediction import UNFAMILIARITY, PredictionFolder

    maps = load_prediction_maps(pred_dir, ortho=ortho, max_side=900)
    panels: list[tuple[str, Any, str]] = [("orthophoto", np.nan_to_num(maps.rgb, nan=1.0), "")]
    panels += [(t, maps.layers[k], k) for k, t in (("height", "height (m above ground)"),
                                                    ("height_std", "height spread (m)")) if k in maps.layers]
    if maps.classes is not None:
        panels.append(("classes", maps.classes, "classes"))
    path = PredictionFolder(pred_dir).layer_path(UNFAMILIARITY)
    if path.exists():
        with rasterio.open(path) as src:
            u = src.read(1, masked=True, out_shape=(maps.grid.height, maps.grid.width), resampling=Resampling.average)
        panels.append(("unfamiliarity", np.ma.filled(u.astype(np.float32), np.nan), UNFAMILIARITY))
    rows, cols = np.nonzero(np.isfinite(maps.layers["height"]))
    crop = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1)) if crop_to_valid else \
        (slice(None), slice(None))
    h, w = maps.layers["height"][crop].shape
    cols = 3 if len(panels) > 4 else 2  # two rows: panels wide enough to read in the text column
    rows = -(-len(panels) // cols)
    side = 3.6
    fig, grid = plt.subplots(rows, cols, figsize=(side * cols, rows * (side * h / w + 0.9) + 0.4),
                             layout="constrained", squeeze=False)
    axes = grid.ravel()
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    for ax, (name, data, key) in zip(axes, panels, strict=False):
        ax.set_axis_off()
        ax.set_title(name, fontsize=10)
        if key == "":
            ax.imshow(data[crop], interpolation="nearest")
        elif key == "classes":
            from matplotlib.colors import ListedColormap

            assert maps.scheme is not None
            k = maps.scheme.num_classes
            ax.imshow(np.ma.masked_greater_equal(data[crop], k), interpolation="nearest", vmin=-0.5, vmax=k - 0.5,
                      cmap=ListedColormap(np.array(maps.scheme.colors, float) / 255))
            from matplotlib.patches import Patch

            ax.legend(handles=[Patch(facecolor=np.array(c) / 255, edgecolor="k", label=n)
                               for c, n in zip(maps.scheme.colors, maps.scheme.names, strict=True)],
                      loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=3, fontsize=8, frameon=False)
        else:
            vals = data[np.isfinite(data)]
            vmax = float(np.percentile(vals, 99)) if vals.size else 1.0
            im = ax.imshow(np.ma.masked_invalid(data[crop]), cmap=layer_cmap(key), vmin=0, vmax=vmax or 1.0,
                           interpolation="nearest")
            bar = fig.colorbar(im, ax=ax, orientation="horizontal", fraction=0.05, pad=0.03)
            bar.set_label("higher = less like training" if key == UNFAMILIARITY else name, fontsize=8)
            bar.ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    return fig


def _short_training(tiles: Path, out: Path, steps: int, model: dict[str, Any] | None = None) -> Any:
    """The demo's network (``aerialmtl demo``'s built-in config), trained ``steps`` steps on ``tiles`` at a constant
    learning rate, without the demo's weight average (over so few steps it would keep the first, untrained
    weights), with one validation at the end and no calibration (too few validation patches to fit one).
    """
    from aerialmtl.demo import DEMO_CONFIG, builtin_config
    from aerialmtl.training.config import load_train_config
    from aerialmtl.training.loop import train

    cfg = load_train_config(builtin_config(DEMO_CONFIG)).with_overrides(
        model=model or {}, data={"num_workers": 0}, calibration={"enabled": False}, seed=0,
        optim={"lr": 1e-3, "ema": None},
        schedule={"max_time_s": None, "max_steps": steps, "val_every": 10_000, "lr_schedule": "constant"})
    return train(cfg, data_dir=tiles, out_dir=out, max_steps=steps, progress=False)


def _qml_colors(qml: Path) -> tuple[list[float], list[str], list[str]]:
    """Values, colours and legend labels of a QGIS style's colour ramp or palette (as QGIS draws the layer)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(qml).getroot()
    items = root.findall(".//colorrampshader/item") or root.findall(".//colorPalette/paletteEntry")
    return ([float(i.get("value", "0")) for i in items], [i.get("color", "#000000") for i in items],
            [i.get("label", "") for i in items])


def styled_figure(pred_dir: Path, title: str) -> Any:
    """The layers of ``pred_dir`` drawn with the colours and legends of the ``.qml`` styles ``predict`` wrote
    beside them, as QGIS shows them when the GeoTIFFs are dragged in (a ramp interpolated between the style's
    stops; a palette for the classes).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import rasterio
    from matplotlib.colors import BoundaryNorm, LinearSegmentedColormap, ListedColormap
    from matplotlib.patches import Patch

    names = [n for n in ("height", "height_std", "classes", "class_entropy", "unfamiliarity")
             if (pred_dir / f"{n}.tif").exists() and (pred_dir / f"{n}.qml").exists()]
    fig, axes = plt.subplots(1, len(names), figsize=(3.0 * len(names), 4.0), layout="constrained")
    for ax, name in zip(np.atleast_1d(axes), names, strict=True):
        values, colors, labels = _qml_colors(pred_dir / f"{name}.qml")
        with rasterio.open(pred_dir / f"{name}.tif") as src:
            data = src.read(1, masked=True)
        if name == "classes":
            cmap = ListedColormap(colors)
            ax.imshow(data, cmap=cmap, norm=BoundaryNorm([v - 0.5 for v in values] + [values[-1] + 0.5], len(colors)),
                      interpolation="nearest")
        else:
            lo, hi = values[0], values[-1]
            stops = [(v - lo) / (hi - lo) if hi > lo else 0.0 for v in values]
            cmap = LinearSegmentedColormap.from_list(name, list(zip(stops, colors, strict=True)))
            ax.imshow(data, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        shown = [(c, t) for c, t in zip(colors, labels, strict=True)]
        if len(shown) > 6:  # a ramp: its first, middle and last stops, as QGIS's legend shows them
            shown = [shown[0], shown[len(shown) // 2], shown[-1]]
        ax.legend(handles=[Patch(facecolor=c, edgecolor="k", label=t) for c, t in shown], loc="upper center",
                  bbox_to_anchor=(0.5, -0.02), fontsize=7, frameon=False, ncol=1 if name == "classes" else 3)
        ax.set_title(f"{name}.tif", fontsize=9)
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    return fig


def town_figures(out: Path) -> dict[str, bytes]:
    """A synthetic training town and test town (:data:`DOCS_TOWN`): tile, train briefly, predict the test town
    with MC dropout, evaluate; the maps in a row, the demo's overview figure and the layers as QGIS styles them.
    """
    from aerialmtl.data.synth import synthesize
    from aerialmtl.demo import preview_figure
    from aerialmtl.evaluation.evaluate import evaluate_prediction
    from aerialmtl.inference.predict import predict_raster
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import TileOptions, tile_dataset

    t = DOCS_TOWN
    train_town = synthesize(out / "train_town", size=t["train_size"], seed=1)
    test = synthesize(out / "test_town", size=t["test_size"], seed=1001)
    tile_dataset(train_town.ortho, out / "tiles", dsm=train_town.dsm, dtm=train_town.dtm, labels=train_town.labels,
                 classes=train_town.classes, progress=False,
                 options=TileOptions(size=t["patch"], stride=t["stride"],
                                     splits=SplitSpec(block_size=t["patch"] * 0.25 * 2, ratios=(0.85, 0.15, 0.0))))
    run = _short_training(out / "tiles", out / "run", t["steps"])
    pred = out / "prediction"
    predict_raster(test.ortho, run.best_checkpoint, pred, mc=t["mc"], precision="fp32", progress=False)
    report = evaluate_prediction(pred, height_ref=test.ndsm, labels_ref=test.labels, classes=test.classes, out=None)
    scores = (f"height MAE {report['height']['mae']:.2f} m, classes OA "
              f"{report['classes']['overall_accuracy']:.2f}")
    RUN_NOTES["town"] = f"synthetic town, {t['steps']} steps: {scores}"
    title = (f"a synthetic test town, {t['test_size']} × {t['test_size']} px of 0.25 m: {scores}\n"
             f"the demo's network after {t['steps']} training steps, T = {t['mc']} MC-dropout samples")
    overview = preview_figure(test.ortho, pred, test.ndsm, test.labels)
    return {"demo_maps.png": _png(products_figure(pred, test.ortho, title), 72),
            "demo_overview.png": _png(overview, 48),
            "qgis_layers.png": _png(styled_figure(pred, "the same layers with the QGIS styles predict wrote "
                                                        "beside them (.qml): colours and legends"), 72)}


def area_figures(work: Path) -> dict[str, bytes]:
    """The small-area recipe on ``samples/autzen_west``, shortened (:data:`DOCS_AREA`): tile at 1 m with the
    sample's split, train the demo's small network (height only, with the recipe's aleatoric head), predict the
    held-out block, evaluate it; the
    maps of the block and the evaluation's two plots.
    """
    from aerialmtl.evaluation.evaluate import evaluate_prediction
    from aerialmtl.inference.predict import predict_raster
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import TileOptions, tile_dataset

    a = DOCS_AREA
    ortho, dsm, dtm = SAMPLE / "ortho_1ft.tif", SAMPLE / "dsm_1m_utm.tif", SAMPLE / "dtm_1m_utm.tif"
    tile_dataset(ortho, work / "tiles", dsm=dsm, dtm=dtm, progress=False,
                 options=TileOptions(size=a["size"], stride=a["stride"], gsd=1.0,
                                     splits=SplitSpec(method="aoi", aoi=str(SAMPLE / "split.geojson"))))
    run = _short_training(work / "tiles", work / "run", a["steps"], model={"aleatoric": True})  # as the recipe
    pred = work / "pred"
    predict_raster(ortho, run.best_checkpoint, pred, mc=a["mc"], aoi=SAMPLE / "test_block.geojson",
                   precision="fp32", progress=False)
    report = evaluate_prediction(pred, dsm_ref=dsm, dtm_ref=dtm, out=work / "eval" / "report.json")
    h = report["height"]
    RUN_NOTES["area"] = (f"autzen_west, {a['steps']} steps: held-out block height MAE {h['mae']:.2f} m, "
                         f"RMSE {h['rmse']:.2f} m ({h['n_pixels']} px)")
    title = (f"samples/autzen_west, the held-out block at 1 m: height MAE {h['mae']:.2f} m against the lidar\n"
             f"the demo's small network with the recipe's aleatoric head, {a['steps']} training steps")
    figures = {"area_maps.png": _png(products_figure(pred, ortho, title, crop_to_valid=True), 72)}
    for name in ("report_height_reliability.png", "report_sparsification.png"):
        if (work / "eval" / name).exists():
            figures[f"area_{name.removeprefix('report_')}"] = (work / "eval" / name).read_bytes()
    return figures


def site_figures() -> dict[str, bytes]:
    """The figures of :data:`FIGURES_DIR`, made once per process (``mkdocs serve`` rebuilds reuse them)."""
    cache = Path(os.environ[FIGURES_CACHE_ENV]) if os.environ.get(FIGURES_CACHE_ENV) else None
    if not _FIGURES and cache is not None and all((cache / n).is_file() for n in FIGURE_NAMES):
        _FIGURES.update({n: (cache / n).read_bytes() for n in FIGURE_NAMES})
    if not _FIGURES:
        import logging
        import time
        import warnings

        log = logging.getLogger("mkdocs.plugins.docs_hooks")
        with tempfile.TemporaryDirectory(prefix="aerialmtl_docs_") as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the reduced runs' own advice (small validation split) is not news here
            for name, make in (("town", town_figures), ("area", area_figures)):
                t = time.perf_counter()
                _FIGURES.update(make(Path(tmp) / name))
                log.info("docs figures: %s in %.0f s", RUN_NOTES.get(name, name), time.perf_counter() - t)
        if cache is not None:
            cache.mkdir(parents=True, exist_ok=True)
            for n, data in _FIGURES.items():
                (cache / n).write_bytes(data)
    return dict(_FIGURES)


# ---- the hooks ------------------------------------------------------------------------------------
def on_startup(**kwargs: Any) -> None:
    """Before the pages are read: the CLI reference's defaults."""
    use_real_defaults()


def on_config(config: Any, **kwargs: Any) -> Any:
    """The notebook's kernel (a child process) leaves out :data:`NOTEBOOK_WARNINGS`."""
    os.environ["PYTHONWARNINGS"] = ",".join(filter(None, (os.environ.get("PYTHONWARNINGS"), NOTEBOOK_WARNINGS)))
    return config


#: A page's link to a benchmarks file itself (``../../bench/RESULTS.md``, ``../../bench/results/TOPIC.md#section``),
#: which works on GitHub and in a clone; the site has those files on its Benchmarks page (``benchmarks.md``
#: includes every topic).
RESULTS_LINK = re.compile(r"\]\((?:\.\./)+bench/(?:RESULTS|results/\w+)\.md(#[^)\s]*)?\)")


def site_links(markdown: str, src_uri: str) -> str:
    """``markdown`` with its links to ``bench/RESULTS.md`` pointed at the site's Benchmarks page (anchors kept)."""
    import posixpath

    target = posixpath.relpath("benchmarks.md", posixpath.dirname(src_uri) or ".")
    return RESULTS_LINK.sub(lambda m: f"]({target}{m.group(1) or ''})", markdown)


def on_page_markdown(markdown: str, page: Any, **kwargs: Any) -> str:
    """Links to ``bench/RESULTS.md`` lead to the Benchmarks page (:func:`site_links`)."""
    return site_links(markdown, page.file.src_uri)


def on_files(files: Any, config: Any, **kwargs: Any) -> Any:
    """Add the figures the build makes (:func:`site_figures`) to the site."""
    from mkdocs.structure.files import File

    for name, data in site_figures().items():
        files.append(File.generated(config, f"{FIGURES_DIR}/{name}", content=data))
    return files


def on_page_content(html: str, page: Any, **kwargs: Any) -> str:
    """Fail the build on a page with :func:`problems`."""
    found = problems(html)
    if found:
        from mkdocs.exceptions import PluginError

        raise PluginError(f"{page.file.src_uri} shows {'; '.join(found)}: fix the page (a notebook cell that "
                          "prints a warning: silence it or fix its cause in the notebook)")
    return html
