"""The uncertainty-maps notebook runs top to bottom on its synthetic mini pipeline and leaves its files."""

from __future__ import annotations

import importlib.util
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import rasterio
from helpers.rasters import write_prediction_folder

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("matplotlib")
pytest.importorskip("ipykernel")

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "uncertainty_maps.ipynb"


def _docs_hooks() -> object:
    """The site's hooks (docs_hooks.py): the site runs the notebook with its ``NOTEBOOK_WARNINGS``."""
    spec = importlib.util.spec_from_file_location("docs_hooks", NOTEBOOK.parents[1] / "docs_hooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_notebook_is_committed_without_outputs() -> None:
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code, "the notebook has no code cells"
    assert all(not c.outputs and c.execution_count is None for c in code), "clear the outputs before committing"
    params = [c for c in code if "parameters" in c.metadata.get("tags", [])]
    assert len(params) == 1 and "PRED_DIR = None" in params[0].source and "AERIALMTL_NB_WORKDIR" in params[0].source


def _run(nb: object, cwd: Path, work: Path) -> dict:
    """Execute ``nb`` in place and return the summary its last cell writes (``WORKDIR/notebook_summary.json``)."""
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(cwd)}})
    client.execute()  # raises CellExecutionError on any failing cell
    result: dict = json.loads((work / "notebook_summary.json").read_text())
    return result


def _page_text(nb: object) -> str:
    """What the notebook's outputs show on the page: streams, plain text and Markdown."""
    parts = []
    for c in nb.cells:  # type: ignore[attr-defined]
        for o in c.get("outputs", []):
            parts.append(o.get("text", ""))
            data = o.get("data", {})
            parts += [data.get("text/markdown", ""), data.get("text/plain", "")]
    return "\n".join(parts)


def test_notebook_on_a_users_own_prediction_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pred = write_prediction_folder(tmp_path / "mine" / "pred", np.random.default_rng(7), size=96)
    work = tmp_path / "work"
    monkeypatch.setenv("AERIALMTL_NB_WORKDIR", str(work))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    at = next(i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", []))
    nb.cells.insert(at + 1, nbformat.v4.new_code_cell(  # what papermill does with injected parameters
        f"PRED_DIR = {str(pred)!r}\nORTHO = {str(pred.parent / 'ortho.tif')!r}\nAREA_SIZE_PX = 32"))
    result = _run(nb, tmp_path, work)
    assert Path(result["prediction"]) == pred
    assert not (work / "prediction").exists() and not (work / "run").exists(), "nothing may be trained"
    assert result["uncertainty"] == {}  # no references given: no curves
    assert {"maps.png", "maps_zoom.png", "areas_class_mutual_info.png"} <= set(result["figures"])
    areas = json.loads((work / "uncertain_areas.json").read_text())
    assert set(areas) == {"height_std", "class_entropy", "class_mutual_info"}
    assert all(len(rows) == 3 and rows[0]["width"] == 32 for rows in areas.values())


@pytest.mark.slow
def test_notebook_runs_the_mini_pipeline(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "work"
    monkeypatch.setenv("AERIALMTL_NB_WORKDIR", str(work))
    monkeypatch.setenv("AERIALMTL_NB_THREADS", "1")  # the test machine is shared: 1 thread is much faster there
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("PYTHONWARNINGS", _docs_hooks().NOTEBOOK_WARNINGS)  # as the site's build runs it
    nb = nbformat.read(NOTEBOOK, as_version=4)
    result = _run(nb, tmp_path, work)
    # what a reader sees: small tables with units, no raw floats, no `nan`, no JSON dump, no stray Out[]
    text = _page_text(nb)
    assert not re.search(r"\d\.\d{12,}", text) and not re.search(r"\bnan\b", text), text
    assert "{" not in text and "| height MAE | " in text, text
    assert not [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "execute_result"
                and "text/plain" in o.get("data", {}) and "image/png" not in o.get("data", {})]
    # the site publishes the outputs as they are, and its build fails on a warning (docs_hooks.py)
    stderr = [o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs
              if o.output_type == "stream" and o.get("name") == "stderr"]
    assert not stderr, stderr

    pred = work / "prediction"
    assert result["prediction"] == "WORKDIR/prediction"  # printed relative: no path of the machine on the site
    for name in ("height.tif", "height_std.tif", "classes.tif", "class_entropy.tif", "class_mutual_info.tif"):
        assert (pred / name).is_file(), name
    assert {"maps.png", "maps_zoom.png", "sparsification.png", "areas_height_std.png", "buildings.png"} <= set(
        result["figures"])
    for name in result["figures"]:
        assert (work / "figures" / name).stat().st_size > 1000
    assert (work / "report.json").is_file()

    u = result["uncertainty"]
    assert set(u) == {"height_std", "class_entropy", "class_mutual_info"}
    for key, s in u.items():
        assert math.isfinite(s["ause"]) and s["ause"] >= 0, key
        assert -1 <= s["spearman"] <= 1, key
        assert s["n_pixels"] > 0 and s["mean_error"] >= 0, key

    buildings = result["buildings"]  # LoD1 section: files written, scored against the test town's footprints
    assert buildings["count"] >= 0 and buildings["files"] == ["buildings.gpkg", "buildings.city.json"]
    for name in buildings["files"]:
        assert (work / name).is_file()
    ev = buildings["evaluation"]
    assert ev["n_reference"] > 0 and 0 <= ev["n_matched"] <= min(ev["n_reference"], buildings["count"])

    with rasterio.open(pred / "height_std.tif") as src:
        b = src.bounds
    for key, (top,) in result["top_areas"].items():
        assert top["rank"] == 1
        assert b.left <= top["left"] < top["right"] <= b.right and b.bottom <= top["bottom"] < top["top"] <= b.top, key
