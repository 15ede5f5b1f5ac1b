"""MkDocs hooks of the documentation site (``hooks:`` in mkdocs.yml): what the site must never show.

* The command-line reference (mkdocs-click) prints ``option.default``; click 8.3+ keeps ``UNSET`` there for
  an option declared without a default, which the table showed as ``Sentinel.UNSET``.
  :func:`use_real_defaults` makes the table show what click itself uses (``False`` for a flag, ``None`` for
  an option that is simply not passed). tests/test_docs.py renders the page through the same function.
* A page that shows a warning, a traceback, ``Sentinel`` or a path of the machine that built the site fails
  the build (:func:`problems`): the notebook pages are run at build time, and a cell that prints a warning
  (a stderr output block) or the build's temporary folder would otherwise be published as it is.
* The pictures of what the package makes (:func:`site_figures`) are made by the build, not pasted: the
  small-area recipe on the sample area ``samples/autzen_west`` with a short training of the demo's small
  network; the pages show them from :data:`FIGURES_DIR`. About 70 s of one CPU core (the build logs it);
  :data:`FIGURES_CACHE_ENV` keeps them between builds.
* The notebook's kernel inherits :data:`NOTEBOOK_WARNINGS` (``PYTHONWARNINGS``, set by :func:`on_config`):
  the one warning a barely trained model may give on the page ("no building pixel", when it found no
  building) is left out there, so that the notebook's cells need no warning-capture code; any other
  warning still fails the build.
"""

from __future__ import annotations

import copy
import html as html_text
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
    stderr = STDERR_BLOCK.search(html)
    if stderr:  # quoted, so that a build on another machine (CI) says which warning it was
        text = html_text.unescape(re.sub(r"<[^>]*>", " ", html[stderr.start():stderr.start() + 4000]))
        found.append(f"a cell's stderr output (a warning or a progress bar): '{' '.join(text.split())[:600]}'")
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
#: The small-area recipe on samples/autzen_west, shortened for the site: patches, stride, steps, MC samples.
#: One short training (about a minute of one CPU core) makes every figure of the site.
DOCS_AREA = {"size": 64, "stride": 32, "steps": 600, "mc": 8}
#: The figures :func:`site_figures` makes.
FIGURE_NAMES = ("area_maps.png", "qgis_layers.png", "area_height_reliability.png", "area_sparsification.png")
#: A folder to keep the figures in between builds (``mkdocs serve`` while writing, a second build): when it
#: holds all of :data:`FIGURE_NAMES` they are read from it instead of made again. Unset: made every build.
FIGURES_CACHE_ENV = "AERIALMTL_DOCS_FIGURES"
#: ``PYTHONWARNINGS`` of the notebook's kernel (see the module docstring).
NOTEBOOK_WARNINGS = "ignore:no building pixel in:UserWarning"
SAMPLE = REPO / "samples" / "autzen_west"
#: Width of the figures in inches at :data:`DPI`: about the text column's width at a 1280-px window, so that a
#: font of N points shows N pixels high (11 px at least, tests/test_docs.py).
WIDTH_IN = 10.0
DPI = 72
#: Font sizes (points) of the figures: titles, labels and ticks, all readable at :data:`WIDTH_IN`.
TITLE_PT, LABEL_PT, TICK_PT = 14, 13, 12
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


def reference_height(grid: Any, dsm: Path, dtm: Path) -> Any:
    """The lidar's height above ground (DSM − DTM, metres, NaN where either is nodata) on ``grid`` (a
    :class:`aerialmtl.io.align.Grid`: the display grid of a prediction), averaged from the lidar's cells.
    """
    import numpy as np
    import rasterio
    from rasterio.warp import Resampling, reproject

    out = []
    for path in (dsm, dtm):
        with rasterio.open(path) as src:
            data = np.full((grid.height, grid.width), np.nan, np.float32)
            reproject(src.read(1, masked=True).filled(np.nan).astype(np.float32), data, src_transform=src.transform,
                      src_crs=src.crs, src_nodata=np.nan, dst_transform=grid.transform, dst_crs=grid.crs,
                      dst_nodata=np.nan, resampling=Resampling.average)
            out.append(data)
    return np.clip(out[0] - out[1], 0, None)


def products_figure(pred_dir: Path, ortho: Path, title: str, reference: tuple[Path, Path] | None = None) -> Any:
    """Two rows of two: the orthophoto, the lidar's height (``reference``: DSM and DTM, if given), the predicted
    height on the same colour scale, and its spread, cropped to the predicted pixels, each with its unit;
    the height colours are those of the QGIS style ``predict`` writes beside ``height.tif``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from aerialmtl.evaluation.maps import layer_cmap, load_prediction_maps

    maps = load_prediction_maps(pred_dir, ortho=ortho, max_side=900)
    height = maps.layers["height"]
    panels: list[tuple[str, Any, str]] = [("the orthophoto", np.nan_to_num(maps.rgb, nan=1.0), "")]
    if reference is not None:
        panels.append(("the lidar's height (reference)", reference_height(maps.grid, *reference), "height"))
    panels.append(("predicted height", height, "height"))
    if "height_std" in maps.layers:
        panels.append(("its spread (MC dropout)", maps.layers["height_std"], "height_std"))
    rows, cols = np.nonzero(np.isfinite(height))
    crop = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    h, w = height[crop].shape
    ncols = 2
    nrows = -(-len(panels) // ncols)
    side = WIDTH_IN / ncols
    fig, grid = plt.subplots(nrows, ncols, figsize=(WIDTH_IN, nrows * (side * h / w + 1.3) + 0.6),
                             layout="constrained", squeeze=False)
    axes = grid.ravel()
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    top = float(np.nanpercentile(height, 99.5))
    if reference is not None:
        top = max(top, float(np.nanpercentile(panels[1][1][crop], 99.5)))
    for ax, (name, data, key) in zip(axes, panels, strict=False):
        ax.set_axis_off()
        ax.set_title(name, fontsize=TITLE_PT)
        if key == "":
            im = ax.imshow(data[crop], interpolation="nearest")
            spacer = fig.colorbar(im, ax=ax, orientation="horizontal", fraction=0.05, pad=0.02)
            spacer.ax.set_visible(False)  # the orthophoto's panel keeps the size of the others
            continue
        vmax = top if key == "height" else float(np.nanpercentile(data[crop], 99))
        im = ax.imshow(np.ma.masked_invalid(data[crop]), cmap=layer_cmap(key), vmin=0, vmax=vmax or 1.0,
                       interpolation="nearest")
        bar = fig.colorbar(im, ax=ax, orientation="horizontal", fraction=0.05, pad=0.02)
        bar.set_label("metres above ground" if key == "height" else "metres", fontsize=LABEL_PT)
        bar.ax.tick_params(labelsize=TICK_PT)
    fig.suptitle(title, fontsize=TITLE_PT)
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


#: The layers :func:`styled_figure` draws, in this order, where the prediction holds them with their style.
STYLED_LAYERS = ("height", "height_std", "classes", "class_entropy", "unfamiliarity", "shadow", "shadow_height")


def styled_figure(pred_dir: Path, title: str) -> Any:
    """The layers of ``pred_dir`` drawn with the colours and legends of the ``.qml`` styles ``predict`` wrote
    beside them, as QGIS shows them when the GeoTIFFs are dragged in (a ramp interpolated between the style's
    stops; a palette for the classes), three to a row.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import rasterio
    from matplotlib.colors import BoundaryNorm, LinearSegmentedColormap, ListedColormap
    from matplotlib.patches import Patch

    names = [n for n in STYLED_LAYERS if (pred_dir / f"{n}.tif").exists() and (pred_dir / f"{n}.qml").exists()]
    with rasterio.open(pred_dir / f"{names[0]}.tif") as src:  # the predicted pixels' box (an --aoi run)
        rows, cols = np.nonzero(~np.ma.getmaskarray(src.read(1, masked=True)))
    crop = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    h, w = rows.max() + 1 - rows.min(), cols.max() + 1 - cols.min()
    ncols = min(3, len(names))
    nrows = -(-len(names) // ncols)
    side = WIDTH_IN / ncols
    fig, axes = plt.subplots(nrows, ncols, figsize=(WIDTH_IN, nrows * (side * h / w + 1.2) + 0.6),
                             layout="constrained", squeeze=False)
    for ax in axes.ravel()[len(names):]:
        ax.set_axis_off()
    for ax, name in zip(axes.ravel(), names, strict=False):
        values, colors, labels = _qml_colors(pred_dir / f"{name}.qml")
        with rasterio.open(pred_dir / f"{name}.tif") as src:
            data = src.read(1, masked=True)[crop]
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
        if len(shown) > 3:  # a ramp: its first, middle and last stops, as QGIS's legend shows them
            shown = [shown[0], shown[len(shown) // 2], shown[-1]]
        ax.legend(handles=[Patch(facecolor=c, edgecolor="k", label=t) for c, t in shown], loc="upper center",
                  bbox_to_anchor=(0.5, -0.02), fontsize=TICK_PT, frameon=False, ncol=1)
        ax.set_title(f"{name}.tif", fontsize=TITLE_PT)
        ax.set_axis_off()
    fig.suptitle(title, fontsize=TITLE_PT)
    return fig


def report_figures(report: dict[str, Any]) -> dict[str, Any]:
    """``evaluate``'s two plots of the height spread (how its intervals cover the errors per height range, and
    the sparsification curve), drawn by ``evaluate``'s own code from ``report``, to be saved at a resolution
    whose smallest text (7 pt) shows at least 11 px high in the text column.
    """
    from aerialmtl.evaluation import report as evaluation_report

    u = report.get("uncertainty") or {}
    made = {"area_height_reliability.png": evaluation_report._height_reliability_figure(u),
            "area_sparsification.png": evaluation_report._sparsification_figure(
                {k: v for k, v in u.items() if k == "height_std"})}
    return {name: fig for name, fig in made.items() if fig is not None}


def area_figures(work: Path) -> dict[str, bytes]:
    """The small-area recipe on ``samples/autzen_west``, shortened (:data:`DOCS_AREA`): tile at 1 m with the
    sample's split, train the demo's small network (height only, with the recipe's aleatoric head), predict the
    held-out block, evaluate it; the maps of the block beside the lidar, the layers as QGIS styles them, and
    the evaluation's two plots of the spread.
    """
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg

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
    report = evaluate_prediction(pred, dsm_ref=dsm, dtm_ref=dtm, out=None)
    h = report["height"]
    RUN_NOTES["area"] = (f"autzen_west, {a['steps']} steps: held-out block height MAE {h['mae']:.2f} m, "
                         f"RMSE {h['rmse']:.2f} m ({h['n_pixels']} px)")
    title = f"samples/autzen_west, the held-out block (1 m pixels): height MAE {h['mae']:.2f} m against the lidar"
    figures = {"area_maps.png": _png(products_figure(pred, ortho, title, reference=(dsm, dtm)), DPI),
               "qgis_layers.png": _png(styled_figure(pred, "the layers in the colours of their QGIS styles"), DPI)}
    for name, fig in report_figures(report).items():
        FigureCanvasAgg(fig)
        buf = io.BytesIO()
        fig.savefig(buf, dpi=DPI * 11 / 7, bbox_inches="tight", format="png")  # 7-pt legends at 11 px
        figures[name] = buf.getvalue()
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
            t = time.perf_counter()
            _FIGURES.update(area_figures(Path(tmp) / "area"))
            log.info("docs figures: %s in %.0f s", RUN_NOTES.get("area", "area"), time.perf_counter() - t)
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


#: A page's link to a file of the lab notebook (``../../bench/RESULTS.md``, ``../../bench/results/TOPIC.md#section``),
#: which works on GitHub and in a clone. The site does not render those files; its Benchmarks page
#: (``benchmarks.md``) has what a user needs and, under "The lab notebook", says where they are.
RESULTS_LINK = re.compile(r"\]\((?:\.\./)+bench/(?:RESULTS|results/\w+)\.md(#[^)\s]*)?\)")
#: Where :func:`site_links` points them.
LAB_NOTEBOOK = "benchmarks.md#the-lab-notebook"


def site_links(markdown: str, src_uri: str) -> str:
    """``markdown`` with its links to the lab notebook's files pointed at the Benchmarks page's section on it."""
    import posixpath

    target = posixpath.relpath(LAB_NOTEBOOK.split("#")[0], posixpath.dirname(src_uri) or ".")
    return RESULTS_LINK.sub(f"]({target}#{LAB_NOTEBOOK.split('#')[1]})", markdown)


def on_page_markdown(markdown: str, page: Any, **kwargs: Any) -> str:
    """Links to the lab notebook's files lead to the Benchmarks page (:func:`site_links`)."""
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
