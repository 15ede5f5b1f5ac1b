"""Predict many orthophotos: in one process, or in many under ``torchrun``.

:func:`predict_many` is what ``aerialmtl predict A.tif B.tif ... --out maps/`` runs. One input writes its
prediction folder at ``out``; several write one folder per input, ``out/<file stem>``, and end with a
VRT mosaic per layer over all of them (``out/<layer>.mosaic.vrt``, :func:`~aerialmtl.io.vrt.mosaic_vrt`:
in the CRS of the first input, at the finest pixel size, inputs in another CRS reprojected on the fly,
the later input shown where inputs overlap).

Under ``torchrun --nproc_per_node N -m aerialmtl predict ...`` every process (rank) loads the model
(on GPU ``LOCAL_RANK`` when CUDA is used; gloo on CPUs, NCCL on GPUs) and takes a contiguous share of
the work: the window rows (bands) of all inputs, in order, cut into N parts of equal size. An input that
falls into one share is predicted whole by its rank; an input cut between ranks is computed in row
strips (each strip also runs the window rows that reach into it, so the rows come out exactly as in a
one-process run), and the rank of its first strip joins the strips into the final COGs. Every
decision (what to skip, what to split) is taken before any rank writes.

``skip_existing`` skips inputs whose folder is complete (``prediction.json`` and every file it lists),
so a large job resumes where it stopped. In one process the first failing input stops the run with its
own message; with several ranks the others finish their shares and the run then fails with a message
naming the input and the rank. Either way no half-written file is ever at a final path.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import torch

from aerialmtl.errors import AerialMTLError, InputError
from aerialmtl.formats.prediction import INFO_FILE, PredictionFolder, mosaic_filename
from aerialmtl.inference.predict import Predictor, PredictResult, StripResult, _record_timings, gdal_env
from aerialmtl.inference.windows import Plan
from aerialmtl.inference.writer import PredictionWriter, check_outputs_free, remove_leftovers
from aerialmtl.io.align import Grid, check_bands, open_raster, reference_grid
from aerialmtl.io.vrt import mosaic_vrt

#: How long a rank waits for the others at the end of its share (they may have more work left).
WAIT_FOR_OTHERS = timedelta(days=7)


class PredictionFailed(AerialMTLError, RuntimeError):
    """An input failed in a distributed run (the message names the input, the rank and the cause)."""


# ---- processes ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ranks:
    """This process's place in a torchrun job (``rank`` 0 of 1 outside torchrun)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @classmethod
    def from_env(cls) -> Ranks:
        """``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` as torchrun sets them."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        return cls(int(os.environ.get("RANK", "0")), world, int(os.environ.get("LOCAL_RANK", "0")))

    def device(self, device: str) -> str:
        """The device of this rank: ``cuda:LOCAL_RANK`` for ``auto``/``cuda`` when GPUs are used."""
        if self.world > 1 and device in ("auto", "cuda") and torch.cuda.is_available():
            torch.cuda.set_device(self.local_rank)
            return f"cuda:{self.local_rank}"
        return device

    def start(self, device: str) -> None:
        """Join the process group (gloo for CPUs, NCCL for GPUs)."""
        import torch.distributed as dist

        if self.world > 1 and not dist.is_initialized():
            dist.init_process_group("nccl" if device.startswith("cuda") else "gloo", timeout=WAIT_FOR_OTHERS)

    def gather(self, obj: Any) -> list[Any]:
        """Every rank's ``obj``, in rank order (a collective: every rank must call it)."""
        if self.world == 1:
            return [obj]
        import torch.distributed as dist

        out: list[Any] = [None] * self.world
        dist.all_gather_object(out, obj)
        return out

    def stop(self) -> None:
        import torch.distributed as dist

        if self.world > 1 and dist.is_initialized():
            dist.destroy_process_group()


# ---- planning ----------------------------------------------------------------------------------
@dataclass
class Target:
    """One input and its prediction folder."""

    ortho: Path
    out: Path
    grid: Grid | None = None
    plan: Plan | None = None


@dataclass(frozen=True)
class Share:
    """Bands ``[band_start, band_stop)`` of target ``target`` (all of them: the whole input)."""

    target: int
    band_start: int
    band_stop: int


def targets_for(orthos: Sequence[str | Path], out: str | Path) -> list[Target]:
    """One input → ``out``; several → ``out/<stem>`` each.

    Raises:
        InputError: several inputs share a file stem (their folders would clash).
    """
    paths = [Path(p) for p in orthos]
    if not paths:
        raise InputError("no orthophoto given; pass one or more GeoTIFFs")
    stems = [p.stem for p in paths]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if len(paths) > 1 and dup:
        raise InputError(f"several inputs share the file stem(s) {dup}, so their sub-folders would clash; "
                         "rename them or run predict once per input")
    return [Target(p, Path(out) if len(paths) == 1 else Path(out) / p.stem) for p in paths]


def check_input(ortho: Path, predictor: Predictor) -> None:
    """Georeferencing and bands of ``ortho`` against the checkpoint (errors name the file and the fix).

    Run for every input before the first prediction starts, so a bad last input fails at once; bands
    beyond the trained ones are reported with a warning when the input runs.
    """
    meta = predictor.meta
    reference_grid(ortho)  # readable, with a CRS and a north-up geotransform
    trained = f"bands {list(meta.bands)}" + (f" ({', '.join(meta.band_names)})" if meta.band_names else "")
    with open_raster(ortho, "orthophoto") as src:
        check_bands(src, meta.bands, "orthophoto", bands_from=f"the checkpoint (trained on {trained})",
                    fix="predict on an orthophoto with those bands, or train a model on this one's bands "
                        "(`aerialmtl tile --bands ...`)")


def partition(band_costs: Sequence[Sequence[float]], world: int) -> list[list[Share]]:
    """Cut the bands of all targets, in order, into ``world`` contiguous shares of about equal cost.

    Args:
        band_costs: per target, the cost of each of its bands.
        world: number of shares.

    Returns:
        Per share (rank), its :class:`Share` list; a target inside one share appears once, whole.
    """
    flat = [(t, b, c) for t, costs in enumerate(band_costs) for b, c in enumerate(costs)]
    total = sum(c for _, _, c in flat)
    shares: list[list[Share]] = [[] for _ in range(world)]
    if not flat:
        return shares
    cum = 0.0
    owner = []
    for _, _, c in flat:  # a band goes to the share its middle falls into
        owner.append(min(world - 1, int((cum + c / 2) * world / total)) if total > 0 else 0)
        cum += c
    for k, (t, b, _) in enumerate(flat):
        r = owner[k]
        last = shares[r][-1] if shares[r] else None
        if last is not None and last.target == t and last.band_stop == b:
            shares[r][-1] = Share(t, last.band_start, b + 1)
        else:
            shares[r].append(Share(t, b, b + 1))
    return shares


# ---- the job -----------------------------------------------------------------------------------
@dataclass
class JobResult:
    """What this process did: results of the inputs it committed, the inputs skipped, the mosaics."""

    results: list[PredictResult] = field(default_factory=list)
    skipped: list[Path] = field(default_factory=list)
    mosaics: dict[str, Path] = field(default_factory=dict)
    ranks: Ranks = field(default_factory=Ranks)


def predict_many(
    orthos: Sequence[str | Path],
    checkpoint: Any,
    out: str | Path,
    *,
    aoi: str | Path | None = None,
    overwrite: bool = False,
    skip_existing: bool = False,
    progress: bool = True,
    on_result: Callable[[PredictResult], None] | None = None,
    **predictor_args: Any,
) -> JobResult:
    """Predict every orthophoto of ``orthos``; see the module docstring.

    Args:
        orthos: the orthophotos.
        checkpoint: checkpoint path or ``(model, meta)``.
        out: prediction folder (one input) or parent folder (several).
        aoi: optional GeoJSON AOI (applied to every input).
        overwrite: replace existing outputs.
        skip_existing: skip inputs whose prediction folder is complete.
        progress: progress bars (rank 0 only).
        on_result: called with each input's result as soon as it is committed.
        predictor_args: :class:`~aerialmtl.inference.predict.Predictor` options (``mc``, ``tile``, ...).

    Returns:
        A :class:`JobResult` for this process.

    Raises:
        OutputExistsError: an input's outputs exist (neither ``overwrite`` nor ``skip_existing``).
        PredictionFailed: an input failed on another rank (distributed runs).
    """
    ranks = Ranks.from_env()
    targets = targets_for(orthos, out)
    device = ranks.device(str(predictor_args.pop("device", "auto")))
    predictor = Predictor(checkpoint, device=device, **predictor_args)
    for t in targets:  # every input usable before the first one takes time
        check_input(t.ortho, predictor)
    ranks.start(str(predictor.device))
    try:
        return _run(predictor, targets, Path(out), ranks, aoi, overwrite, skip_existing, progress, on_result)
    finally:
        ranks.stop()


def _run(predictor: Predictor, targets: list[Target], out: Path, ranks: Ranks, aoi: str | Path | None,
         overwrite: bool, skip_existing: bool, progress: bool,
         on_result: Callable[[PredictResult], None] | None) -> JobResult:
    job = JobResult(ranks=ranks)
    todo = []
    for k, t in enumerate(targets):
        if skip_existing and PredictionFolder(t.out).is_complete():
            job.skipped.append(t.ortho)
            continue
        todo.append(k)
    if not overwrite:  # once per input, before any work
        files = [s.filename for s in predictor.layers] + [INFO_FILE]
        for k in todo:
            check_outputs_free(targets[k].out, files, overwrite=False)
    for k in todo:
        t = targets[k]
        t.grid = predictor.grid(t.ortho, warn=ranks.rank == 0)
        t.plan = predictor.plan(t.grid)
    plans = {k: targets[k].plan for k in todo}
    costs = [[float(len(p.cols.starts) * p.rows.size * p.cols.size)] * len(p.bands)
             for p in plans.values() if p is not None]
    shares = partition(costs, ranks.world)
    mine = [Share(todo[s.target], s.band_start, s.band_stop) for s in shares[ranks.rank]]
    split = {todo[s.target] for r in shares for s in r
             if s.band_start > 0 or s.band_stop < len(targets[todo[s.target]].plan.bands)}  # type: ignore[union-attr]
    if ranks.rank == 0:  # hidden files of killed runs: removed before any rank writes
        for k in todo:
            remove_leftovers(targets[k].out)
    ranks.gather(None)  # barrier

    failures: list[tuple[str, int, str]] = []
    strips: dict[int, tuple[int, StripResult]] = {}
    writers: dict[int, PredictionWriter] = {}
    with gdal_env():
        for share in mine:
            t = targets[share.target]
            if share.target not in split:
                try:
                    res = predictor.run(t.ortho, t.out, aoi=aoi, overwrite=overwrite, grid=t.grid,
                                        progress=progress and ranks.rank == 0, check_outputs=False)
                except Exception as exc:
                    if ranks.world == 1:
                        raise
                    failures.append((str(t.ortho), ranks.rank, _one_line(exc)))
                    continue
                job.results.append(res)
                if on_result is not None:
                    on_result(res)
                continue
            writer = None
            try:
                assert t.grid is not None and t.plan is not None
                rows = (t.plan.bands[share.band_start].out_start, t.plan.bands[share.band_stop - 1].out_stop)
                if share.band_start == 0:
                    predictor.warn_unused_bands(t.ortho)
                writer = PredictionWriter(t.out, t.grid, predictor.layers, overwrite=overwrite, rows=rows,
                                          clean=False, check=False)
                t0 = time.perf_counter()
                res_strip = predictor.compute(t.ortho, t.grid, t.plan, writer, aoi=aoi,
                                              bands=(share.band_start, share.band_stop),
                                              progress=progress and ranks.rank == 0)
                writer.finish()
                res_strip.timings["write"] = writer.seconds_writing
                res_strip.timings["strip_total"] = time.perf_counter() - t0
                strips[share.target] = (rows[0], res_strip)
                if share.band_start == 0:
                    writers[share.target] = writer  # this rank joins the strips
                else:
                    writer = None
            except Exception as exc:
                if writer is not None:
                    writer.abort()
                failures.append((str(t.ortho), ranks.rank, _one_line(exc)))

    # every rank's strips and failures; then the first strip's rank commits each split input
    gathered = ranks.gather((strips, failures))
    all_failures = [f for _, fs in gathered for f in fs]
    failed = {f[0] for f in all_failures}
    for k, writer in writers.items():
        t = targets[k]
        parts = [(start, res) for st, _ in gathered for kk, (start, res) in st.items() if kk == k]
        if str(t.ortho) in failed:
            writer.abort()
            remove_leftovers(t.out)
            continue
        try:
            res = _commit_split(predictor, t, writer, parts, aoi, len(parts))
        except Exception as exc:
            failures.append((str(t.ortho), ranks.rank, _one_line(exc)))
            all_failures.append(failures[-1])
            continue
        job.results.append(res)
        if on_result is not None:
            on_result(res)
    if ranks.world > 1:
        all_failures = [f for fs in ranks.gather(failures) for f in fs]
    if all_failures:
        if ranks.rank == 0:  # strips of failed inputs: hidden files only, final paths untouched
            for t in targets:
                if str(t.ortho) in {f[0] for f in all_failures} and t.out.is_dir():
                    remove_leftovers(t.out)
        ortho, rank, message = all_failures[0]
        more = f" ({len(all_failures) - 1} more input(s) failed too)" if len(all_failures) > 1 else ""
        raise PredictionFailed(
            f"rank {rank} failed on input '{ortho}': {message}{more}; the other inputs are complete: fix it and "
            "re-run with ‹skip_existing=True› to finish"
        )
    if len(targets) > 1 and ranks.rank == 0:
        job.mosaics = write_mosaics(predictor, targets, out)
    ranks.gather(None)  # nobody leaves before the mosaics exist
    return job


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or exc.__class__.__name__


def _commit_split(predictor: Predictor, t: Target, writer: PredictionWriter, parts: list[tuple[int, StripResult]],
                  aoi: str | Path | None, processes: int) -> PredictResult:
    """Join the strips of a split input into its COGs (called by the rank of its first strip)."""
    assert t.grid is not None and t.plan is not None
    t0 = time.perf_counter()
    computed = sum(r.windows_computed for _, r in parts)
    timings: dict[str, float] = {}
    for _, r in parts:  # the slowest strip's stage times
        for key, v in r.timings.items():
            timings[key] = max(timings.get(key, 0.0), v)
    info = predictor.info(t.ortho, t.grid, t.plan, aoi, computed, timings, processes=processes)
    files = writer.commit(info, strips=[start for start, _ in parts])
    timings["cog"] = time.perf_counter() - t0
    timings["total"] = timings.get("strip_total", 0.0) + timings["cog"]
    _record_timings(files["prediction"], timings)
    out_px = t.grid.width * t.grid.height
    return PredictResult(t.out, files, t.grid, predictor.mc, t.plan.num_windows, computed,
                         predictor.overlap_factor(t.plan, computed), t.plan.overlap_factor,
                         out_px / 1e6 / max(timings["total"], 1e-9), timings, t.ortho)


def write_mosaics(predictor: Predictor, targets: Sequence[Target], out: Path) -> dict[str, Path]:
    """One VRT per layer over every input's folder (:func:`~aerialmtl.formats.prediction.mosaic_filename`)."""
    mosaics = {}
    for spec in predictor.layers:
        sources = [t.out / spec.filename for t in targets if (t.out / spec.filename).is_file()]
        if sources:
            mosaics[spec.name] = mosaic_vrt(out / mosaic_filename(spec.name), sources, categorical=spec.categorical)
    return mosaics


__all__ = ["JobResult", "PredictionFailed", "Ranks", "Share", "Target", "check_input", "partition",
           "predict_many", "targets_for", "write_mosaics"]
