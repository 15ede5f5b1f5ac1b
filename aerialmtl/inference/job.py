"""One input predicted into its prediction folder: the job, apart from the model that computes it.

An :class:`InputJob` is one orthophoto (:class:`~aerialmtl.inference.ortho.OrthoInput`) and its
prediction folder. It owns the writer's whole life: the claim of the folder's outputs and the removal
of a killed run's leftovers (through :func:`~aerialmtl.inference.writer.prediction_folder`, the output
owner), the staging files of each strip it computes (:meth:`InputJob.strip`), their abort, and the commit
(:meth:`InputJob.commit`): COGs, then ``prediction.json`` written once, timings included
(:class:`~aerialmtl.formats.prediction.PredictionRecord`), then the :class:`PredictResult`.

The model — loaded once, with its settings, its output schema and the window loop — is the
:class:`~aerialmtl.inference.predict.Predictor`; a job only needs what :class:`JobModel` lists of it.
The whole raster is the one-strip case; a ``torchrun`` rank computes one strip of an input it shares
(:mod:`aerialmtl.inference.jobs`), and the rank of the first strip commits them all.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from aerialmtl._version import __version__
from aerialmtl.errors import InputError
from aerialmtl.formats.prediction import (
    ALL_FILES,
    GridInfo,
    LayerSpec,
    PredictionRecord,
    folder_files,
)
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.stitch import Block
from aerialmtl.inference.writer import PredictionWriter, prediction_folder
from aerialmtl.io.align import Grid


@dataclass(frozen=True)
class PredictResult:
    """What one input's prediction wrote and how long it took.

    Attributes:
        out_dir: the prediction folder.
        files: layer name → final path (``"prediction"`` is ``prediction.json``).
        mc: MC-dropout samples T.
        windows_total, windows_computed: windows in the plan / actually run through the model.
        overlap_factor: pixels computed / output pixels (computed windows only).
        plan_overlap_factor: the same if every window were computed.
        megapixels_per_s: output megapixels per second of total time.
        timings: seconds per stage (``read`` and ``write`` run in background threads and overlap the
            others; ``model``, ``stitch_write`` (stitching plus waiting for the writer), ``strip_total``
            (the slowest strip, or the whole raster), ``cog`` (the conversion to COGs), ``total`` (up to the
            end of the conversion; ``prediction.json`` records these same numbers).
        ortho: the orthophoto.
    """

    out_dir: Path
    files: dict[str, Path]
    grid: Grid
    mc: int
    windows_total: int
    windows_computed: int
    overlap_factor: float
    plan_overlap_factor: float
    megapixels_per_s: float
    timings: dict[str, float] = field(default_factory=dict)
    ortho: str | Path | None = None


@dataclass
class StripResult:
    """What one strip of window rows (or the whole raster) computed; travels between ranks.

    Attributes:
        windows_computed: windows run through the model.
        timings: seconds per stage (see :class:`PredictResult`).
        row_start: the first grid row the strip wrote (its staging files are named after it).
    """

    windows_computed: int
    timings: dict[str, float]
    row_start: int = 0


class JobModel(Protocol):
    """What a job needs of the model that computes it (:class:`~aerialmtl.inference.predict.Predictor`)."""

    @property
    def layers(self) -> tuple[LayerSpec, ...]:
        """The output schema, in file order."""
        ...

    @property
    def mc(self) -> int:
        """MC-dropout samples T."""
        ...

    def compute(self, src: OrthoInput, rows: tuple[int, int], write: Callable[[Block], None], *,
                aoi: str | Path | None = None, progress: bool = True) -> StripResult:
        """Read, run and stitch window rows ``rows`` of ``src``, handing each finished block to ``write``."""
        ...

    def record_settings(self, src: OrthoInput, aoi: str | Path | None) -> dict[str, Any]:
        """The model's and the settings' fields of ``prediction.json`` for ``src``."""
        ...


class InputJob:
    """Predict one input into its prediction folder; see the module docstring.

    Args:
        model: what computes the maps.
        src: the input (:meth:`Predictor.open <aerialmtl.inference.predict.Predictor.open>`).
        out: its prediction folder.
        aoi: optional GeoJSON AOI (windows outside are not computed, pixels outside are nodata).
        overwrite: replace existing outputs.
    """

    def __init__(self, model: JobModel, src: OrthoInput, out: str | Path, *, aoi: str | Path | None = None,
                 overwrite: bool = False) -> None:
        self.model, self.src, self.out, self.aoi, self.overwrite = model, src, Path(out), aoi, overwrite
        self.writer: PredictionWriter | None = None  # the first strip's: the one that commits

    def strip(self, window_rows: tuple[int, int] | None = None, *, check_outputs: bool = True,
              progress: bool = True) -> StripResult:
        """Compute window rows ``[start, stop)`` of the input (default all) into staging files.

        The whole raster, or the first strip of a shared input, keeps its writer for :meth:`commit`; another
        strip's staging files are left for the committing rank (its writer is closed here).

        Args:
            window_rows: the strip; ``None`` is the whole raster.
            check_outputs: refuse existing outputs (whole raster only: a shared input was checked by the
                job, once, before any rank wrote).
            progress: a progress bar.

        Raises:
            OutputExistsError: outputs exist (``check_outputs``, without ``overwrite``).
        """
        t0 = time.perf_counter()
        plan = self.src.plan
        n_rows = len(plan.window_rows)
        start, stop = (0, n_rows) if window_rows is None else window_rows
        whole = (start, stop) == (0, n_rows)
        rows = (plan.window_rows[start].out_start, plan.window_rows[stop - 1].out_stop)
        if whole:
            folder = prediction_folder(self.out)
            if check_outputs:
                folder.claim(folder_files(s.name for s in self.model.layers), self.overwrite)
            folder.remove_leftovers(ALL_FILES)  # hidden files of a killed run (under the job's lock)
        writer = PredictionWriter(self.out, self.src.grid, self.model.layers, overwrite=self.overwrite,
                                  rows=None if whole else rows)
        try:
            res = self.model.compute(self.src, (start, stop), writer.write, aoi=self.aoi, progress=progress)
            t1 = time.perf_counter()
            writer.finish()
            res.timings["stitch_write"] += time.perf_counter() - t1
            res.timings["write"] = writer.seconds_writing
        except BaseException:
            writer.abort()
            raise
        res.timings["strip_total"] = time.perf_counter() - t0
        res.row_start = rows[0]
        if start == 0:
            self.writer = writer
        return res

    def abort(self) -> None:
        """Remove this job's hidden files (its writer's, and a failed shared input's leftovers)."""
        if self.writer is not None:
            self.writer.abort()
            self.writer = None

    def commit(self, strips: Sequence[StripResult], *, processes: int = 1,
               started: float | None = None) -> PredictResult:
        """Join the strips (this job's first one among them) into the final COGs and ``prediction.json``;
        aborts if that fails.

        Args:
            strips: every strip of the input, from every rank.
            processes: ranks that computed them.
            started: ``time.perf_counter()`` when the job started (default: the slowest strip's time).

        Raises:
            InputError: the input changed while it was read.
        """
        writer = self.writer
        assert writer is not None, "commit needs the job that computed the first strip"
        t0 = time.perf_counter()
        computed = sum(r.windows_computed for r in strips)
        timings: dict[str, float] = {}
        for r in strips:  # the slowest strip's stage times
            for key, v in r.timings.items():
                timings[key] = max(timings.get(key, 0.0), v)
        before = (t0 - started) if started is not None else timings.get("strip_total", 0.0)
        try:
            moved = self.src.changed()  # maps of a file replaced under the run would be recorded as the new file's
            if moved is not None:
                raise InputError(
                    f"orthophoto '{self.src.path}' changed while it was read ({moved}), so its maps mix two versions "
                    f"and were not written to '{self.out}': re-run when the file is no longer being written or "
                    "replaced")
            writer.convert(strips=[r.row_start for r in strips])
            timings["cog"] = time.perf_counter() - t0
            timings["total"] = before + timings["cog"]
            files = writer.publish(self.record(computed, timings, processes))
        except BaseException:
            self.abort()
            raise
        self.writer = None
        return self.result(files, computed, timings)

    def record(self, computed: int, timings: dict[str, float], processes: int = 1) -> PredictionRecord:
        """The ``prediction.json`` of this input (:class:`~aerialmtl.formats.prediction.PredictionRecord`)."""
        src, plan, grid = self.src, self.src.plan, self.src.grid
        return PredictionRecord(
            aerialmtl_version=__version__,
            orthophoto=str(src.path),
            window_size=[plan.rows.size, plan.cols.size],
            processes=processes,
            aoi=None if self.aoi is None else str(self.aoi),
            grid=GridInfo(crs=grid.crs.to_string(), transform=list(grid.transform)[:6], width=grid.width,
                          height=grid.height, gsd=grid.gsd),
            resampled_from_gsd=src.resampled_from,
            input_rescale=None if src.rescale is None else list(src.rescale),
            windows_total=plan.num_windows,
            windows_computed=computed,
            overlap_factor=plan.computed_overlap(computed),
            plan_overlap_factor=plan.overlap_factor,
            timings_s=dict(timings),
            **self.model.record_settings(src, self.aoi),
        )

    def result(self, files: dict[str, Path], computed: int, timings: dict[str, float]) -> PredictResult:
        """The :class:`PredictResult` of the committed input (warns when every layer is nodata)."""
        src, plan, grid = self.src, self.src.plan, self.src.grid
        if computed == 0 and plan.num_windows > 0:  # complete, but a map of nodata only: say so
            where = f" inside the AOI '{self.aoi}'" if self.aoi is not None else ""
            warnings.warn(f"orthophoto '{src.path}' has no valid pixel{where} (all nodata or masked): every layer in "
                          f"'{self.out}' is nodata; check the orthophoto's nodata value and mask", stacklevel=3)
        out_px = grid.width * grid.height
        return PredictResult(self.out, files, grid, self.model.mc, plan.num_windows, computed,
                             plan.computed_overlap(computed), plan.overlap_factor,
                             out_px / 1e6 / max(timings["total"], 1e-9), timings, src.path)


__all__ = ["InputJob", "JobModel", "PredictResult", "StripResult"]
