"""One input predicted into its prediction folder: the job, apart from the model that computes it.

An :class:`InputJob` is one orthophoto (:class:`~aerialmtl.inference.ortho.OrthoInput`) and its
prediction folder, which it owns: it creates it, claims its outputs (:meth:`InputJob.claim`), removes a
killed run's leftovers (:meth:`InputJob.clean`) and an earlier run's stale layers, and removes the folder
again when a failed run created it. Its writers (:class:`~aerialmtl.inference.writer.PredictionWriter`, one
per strip it computes, :meth:`InputJob.strip`) own only their staging files. The commit
(:meth:`InputJob.commit`) writes the COGs, then ``prediction.json`` once, timings included
(:class:`~aerialmtl.formats.prediction.PredictionRecord`), then returns the :class:`PredictResult`.
:func:`prediction_folder` is the folder as :mod:`aerialmtl.io.outputs` owns it, for the job and the jobs
(:mod:`aerialmtl.inference.jobs`) alone.

The model — loaded once, with its settings, its output schema and the window loop — is the
:class:`~aerialmtl.inference.model.Predictor`; a job only needs what :class:`JobModel` lists of it.
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
    INFO_FILE,
    GridInfo,
    LayerSpec,
    PredictionFolder,
    PredictionRecord,
    folder_files,
)
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.stitch import Block
from aerialmtl.inference.strips import StripResult
from aerialmtl.inference.writer import PredictionWriter
from aerialmtl.io.align import Grid
from aerialmtl.io.outputs import OutputFolder, make_output_dir


def prediction_folder(out_dir: str | Path, option: str = "out_dir") -> OutputFolder:
    """``out_dir`` as :mod:`aerialmtl.io.outputs` owns it.

    Its claim (existing outputs refused without ``overwrite``) and the removal of a killed run's hidden files.

    The lock is not taken here: the job holds it (:class:`~aerialmtl.io.outputs.OutputFolder` entered).
    """
    return OutputFolder(out_dir, "predict", option=option, what="prediction folder", lock=False)


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
        timings: seconds per stage (``read``, ``stitch_write`` and ``write`` run in threads of their own and
            overlap the others; ``model``, ``stitch_write`` (stitching plus waiting for the writer), ``strip_total``
            (the slowest strip, or the whole raster), ``cog`` (the conversion to COGs), ``total`` (up to the
            end of the conversion; ``prediction.json`` records these same numbers).
        ortho: the orthophoto.
        sun: ``prediction.json``'s ``sun`` (the sun of the shadow layers, where it came from, or why they are
            off); ``None`` when the shadow features are off for the whole run.
        sun_tune: ``prediction.json``'s ``sun_tune`` (what ``--sun-tune`` did), ``None`` when the run did not tune.
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
    sun: dict[str, Any] | None = None
    sun_tune: dict[str, Any] | None = None


class JobModel(Protocol):
    """What a job needs of the model that computes it (:class:`~aerialmtl.inference.model.Predictor`)."""

    @property
    def layers(self) -> tuple[LayerSpec, ...]:
        """The output schema, in file order."""
        ...

    @property
    def mc(self) -> int:
        """MC-dropout samples T."""
        ...

    @property
    def aoi(self) -> str | Path | None:
        """The AOI of the run (the settings')."""
        ...

    def compute(self, src: OrthoInput, rows: tuple[int, int], write: Callable[[Block], None], *,
                progress: bool = True) -> StripResult:
        """Read, run and stitch window rows ``rows`` of ``src``, handing each finished block to ``write``."""
        ...

    def record_settings(self, src: OrthoInput) -> dict[str, Any]:
        """The model's and the settings' fields of ``prediction.json`` for ``src``."""
        ...


class InputJob:
    """Predict one input into its prediction folder; see the module docstring.

    Args:
        model: what computes the maps.
        src: the input (:meth:`Predictor.open <aerialmtl.inference.model.Predictor.open>`).
        out: its prediction folder.
        overwrite: replace existing outputs.
        option: the parameter naming the folder, for messages.
    """

    def __init__(self, model: JobModel, src: OrthoInput, out: str | Path, *, overwrite: bool = False,
                 option: str = "out_dir") -> None:
        self.model, self.src, self.out, self.overwrite = model, src, Path(out), overwrite
        self.aoi = model.aoi
        self.writer: PredictionWriter | None = None  # the first strip's: the one that commits
        self.folder = prediction_folder(self.out, option)
        self._created = False

    def claim(self) -> None:
        """Refuse existing outputs (unless ``overwrite``).

        Raises:
            OutputExistsError: outputs exist and ``overwrite`` is false.
        """
        self.folder.claim(folder_files(s.name for s in self.model.layers), self.overwrite)

    def clean(self) -> None:
        """Remove the hidden files of a killed or failed run here (called under the job's lock)."""
        self.folder.remove_leftovers(ALL_FILES)

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
            if check_outputs:
                self.claim()
            self.clean()  # hidden files of a killed run (under the job's lock)
        writer = self._writer(None if whole else rows)
        try:
            res = self.model.compute(self.src, (start, stop), writer.write, progress=progress)
            t1 = time.perf_counter()
            writer.finish()
            res.timings["stitch_write"] += time.perf_counter() - t1
            res.timings["write"] = writer.seconds_writing
        except BaseException:
            writer.abort()
            self._after_abort(whole)
            raise
        res.timings["strip_total"] = time.perf_counter() - t0
        res.row_start = rows[0]
        if start == 0:
            self.writer = writer
        return res

    def _writer(self, rows: tuple[int, int] | None) -> PredictionWriter:
        """A writer of grid rows ``rows`` (``None``: all) into the folder, created here when missing."""
        self._created = make_output_dir(self.out) or self._created
        return PredictionWriter(self.out, self.src.grid, self.model.layers, rows=rows)

    def _after_abort(self, whole: bool) -> None:
        """Clean up after a writer's abort.

        The whole input's hidden files, and the folder if this job created it and it is empty (a strip leaves the
        others' files: other processes may still be writing theirs).
        """
        if whole:
            self.clean()
        if self._created:
            try:
                self.out.rmdir()
            except OSError:
                pass

    def abort(self) -> None:
        """Remove this job's hidden files (its writer's, and a failed input's leftovers)."""
        if self.writer is not None:
            self.writer.abort()
            self.writer = None
        self._after_abort(True)

    def _replace_earlier(self, produced: list[str]) -> None:
        """With ``overwrite``, remove an earlier run's layers this run does not produce.

        Those its ``prediction.json`` lists (it proves they are its own) are removed, ``prediction.json`` first
        (never a complete-looking mix).
        """
        if not self.overwrite:
            return
        owned = PredictionFolder(self.out).owned_files()
        self.folder.remove_owned([INFO_FILE])
        self.folder.remove_owned(f for f in owned if f not in set(produced))

    def commit(self, strips: Sequence[StripResult], *, processes: int = 1,
               started: float | None = None) -> PredictResult:
        """Join the strips (this job's first one among them) into the final COGs and ``prediction.json``.

        Aborts if that fails. :meth:`commit_files`, then :meth:`result`.

        Args:
            strips: every strip of the input, from every rank.
            processes: ranks that computed them.
            started: ``time.perf_counter()`` when the job started (default: the slowest strip's time).

        Raises:
            InputError: the input changed while it was read.
        """
        fields = self.model.record_settings(self.src)
        return self.result(*self.commit_files(strips, processes=processes, started=started, fields=fields), fields)

    def commit_files(self, strips: Sequence[StripResult], *, processes: int = 1, started: float | None = None,
                     fields: dict[str, Any] | None = None) -> tuple[dict[str, Path], int, dict[str, float]]:
        """The files of :meth:`commit` (COGs, styles, STAC item, ``prediction.json``), put at their final paths;
        aborts if that fails. Touches this job's folder only, and warns of nothing, so that it may run in a thread
        beside the next input's strip (:mod:`aerialmtl.inference.jobs`), given the model's ``fields`` of
        ``prediction.json`` (:meth:`JobModel.record_settings`) from the caller's thread (default: asked here).

        Returns:
            layer name → final path, the windows computed, the stage times: :meth:`result`'s arguments.
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
            produced = writer.stage(self.record(computed, timings, processes, fields))
            self._replace_earlier(produced)
            files = writer.publish()
        except BaseException:
            self.abort()
            raise
        self.writer = None
        return files, computed, timings

    def record(self, computed: int, timings: dict[str, float], processes: int = 1,
               fields: dict[str, Any] | None = None) -> PredictionRecord:
        """The ``prediction.json`` of this input (:class:`~aerialmtl.formats.prediction.PredictionRecord`); the
        model's ``fields`` as :meth:`JobModel.record_settings` gives them (default: asked here).
        """
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
            **(self.model.record_settings(src) if fields is None else fields),
        )

    def result(self, files: dict[str, Path], computed: int, timings: dict[str, float],
               fields: dict[str, Any]) -> PredictResult:
        """The :class:`PredictResult` of the committed input (warns when every layer is nodata); ``fields``: the
        model's fields of its ``prediction.json`` (:meth:`JobModel.record_settings`, as :meth:`commit_files` got them).
        """
        src, plan, grid = self.src, self.src.plan, self.src.grid
        if computed == 0 and plan.num_windows > 0:  # complete, but a map of nodata only: say so
            where = f" inside the AOI '{self.aoi}'" if self.aoi is not None else ""
            warnings.warn(f"orthophoto '{src.path}' has no valid pixel{where} (all nodata or masked): every layer in "
                          f"'{self.out}' is nodata; check the orthophoto's nodata value and mask", stacklevel=3)
        out_px = grid.width * grid.height
        return PredictResult(self.out, files, grid, self.model.mc, plan.num_windows, computed,
                             plan.computed_overlap(computed), plan.overlap_factor,
                             out_px / 1e6 / max(timings["total"], 1e-9), timings, src.path, fields.get("sun"),
                             fields.get("sun_tune"))


__all__ = ["InputJob", "JobModel", "PredictResult", "StripResult", "prediction_folder"]
