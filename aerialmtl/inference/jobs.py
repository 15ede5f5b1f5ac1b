"""Predict orthophotos: the one orchestrator, in one process or in many under ``torchrun``.

:func:`predict_raster` is the one-input case of :func:`predict_many` (the same code path, its one result).
:func:`predict_many` is what ``aerialmtl predict A.tif B.tif ... --out maps/`` runs. One input writes its
prediction folder at ``out``; several write one folder per input, ``out/<file stem>``, and end with a
VRT mosaic per layer over all of them (``out/<layer>.mosaic.vrt``, :func:`~aerialmtl.io.vrt.mosaic_vrt`:
in the CRS of the first input, at the finest pixel size, inputs in another CRS reprojected on the fly,
the later input shown where inputs overlap).

Under ``torchrun --nproc_per_node N -m aerialmtl predict ...`` every process (rank) loads the model
(on GPU ``LOCAL_RANK`` when CUDA is used; gloo on CPUs, NCCL on GPUs) and takes a contiguous share of
the work: the window rows of all inputs, in order, cut into N parts of equal size. An input that falls
into one share is predicted whole by its rank (one strip, one
:class:`~aerialmtl.inference.job.InputJob`); an input cut between ranks is computed in strips of window rows
(:meth:`~aerialmtl.inference.job.InputJob.strip`; each strip also runs the window rows that reach into
it, so the rows come out exactly as in a one-process run), and the rank of its first strip joins the
strips into the final COGs (:meth:`~aerialmtl.inference.job.InputJob.commit`); on a GPU a whole input's COGs are
built in a thread while the next input computes (:mod:`~aerialmtl.inference.commits`). Every decision (what to
skip, which inputs to share) is taken before any rank writes. Each input's header is read once
(:class:`~aerialmtl.inference.ortho.OrthoInput`) and travels with it; the process group, device and GDAL
settings come from :mod:`aerialmtl.runtime`, as for training. Predict's settings are one
:class:`~aerialmtl.inference.settings.PredictSettings`, built once by the caller and handed to the model
(:class:`~aerialmtl.inference.model.Predictor`) unchanged but for the rank's device.

``skip_existing`` skips inputs whose folder is complete for this run (``prediction.json`` of the same
model, settings and input, every layer whole: :meth:`~aerialmtl.formats.prediction.PredictionFolder.check`),
so a large job resumes where it stopped; an earlier run's outputs that are not (another model, ``--mc``,
a changed input, a truncated layer) are recomputed and :attr:`JobResult.recomputed` says why. The job
holds its output folders' locks (rank 0, for the whole job), so two jobs never write one folder.

In one process the first failing input stops the run with its own message; with several ranks the
others finish their shares and the run then fails with a message naming the input and the rank. Either
way no half-written file is ever at a final path.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from aerialmtl import runtime
from aerialmtl.errors import AerialMTLError, InputError, OutputExistsError, PeerFailure
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.formats.prediction import (
    LAYERS,
    PredictionFolder,
    folder_files,
    mosaic_filename,
    mosaic_files,
    mosaic_style_filename,
)
from aerialmtl.formats.qgis_style import write_raster_style
from aerialmtl.formats.stac import collection_files, write_collection
from aerialmtl.inference.commits import Commits, commits_in_thread, one_line
from aerialmtl.inference.job import InputJob, PredictResult, StripResult, prediction_folder
from aerialmtl.inference.model import Predictor
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.settings import PredictSettings, settings_of
from aerialmtl.inference.windows import Plan
from aerialmtl.io.outputs import OutputFolder, check_local_output, check_not_input
from aerialmtl.io.paths import gdal_path, raster_stem
from aerialmtl.io.vrt import mosaic_vrt


# ---- planning ----------------------------------------------------------------------------------
@dataclass
class Target:
    """One input, its prediction folder and, once opened, its header (:class:`OrthoInput`)."""

    ortho: str
    out: Path
    src: OrthoInput | None = None

    @property
    def plan(self) -> Plan | None:
        """The input's window plan, once opened."""
        return None if self.src is None else self.src.plan


@dataclass(frozen=True)
class Share:
    """Window rows ``[start, stop)`` of target ``target`` (all of them: the whole input)."""

    target: int
    start: int
    stop: int


def targets_for(orthos: Sequence[str | Path], out: str | Path, option: str = "out") -> list[Target]:
    """One input → ``out``; several → ``out/<stem>`` each (inputs may be URLs: :mod:`aerialmtl.io.paths`).

    Raises:
        InputError: several inputs share a file stem (their folders would clash).
    """
    check_local_output(out, option)
    paths = [gdal_path(p) for p in orthos]
    if not paths:
        raise InputError("no orthophoto given; pass one or more GeoTIFFs")
    stems = [raster_stem(p) for p in paths]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if len(paths) > 1 and dup:
        raise InputError(f"several inputs share the file stem(s) {dup}, so their sub-folders would clash; "
                         "rename them or run predict once per input")
    return [Target(p, Path(out) if len(paths) == 1 else Path(out) / s) for p, s in zip(paths, stems)]


def partition(row_costs: Sequence[Sequence[float]], world: int) -> list[list[Share]]:
    """Cut the window rows of all targets, in order, into ``world`` contiguous shares of about equal cost.

    Args:
        row_costs: per target, the cost of each of its window rows.
        world: number of shares.

    Returns:
        Per share (rank), its :class:`Share` list; a target inside one share appears once, whole.
    """
    flat = [(t, b, c) for t, costs in enumerate(row_costs) for b, c in enumerate(costs)]
    total = sum(c for _, _, c in flat)
    shares: list[list[Share]] = [[] for _ in range(world)]
    if not flat:
        return shares
    cum = 0.0
    owner = []
    for _, _, c in flat:  # a window row goes to the share its middle falls into
        owner.append(min(world - 1, int((cum + c / 2) * world / total)) if total > 0 else 0)
        cum += c
    for k, (t, b, _) in enumerate(flat):
        r = owner[k]
        last = shares[r][-1] if shares[r] else None
        if last is not None and last.target == t and last.stop == b:
            shares[r][-1] = Share(t, last.start, b + 1)
        else:
            shares[r].append(Share(t, b, b + 1))
    return shares


# ---- the job -----------------------------------------------------------------------------------
@dataclass
class JobResult:
    """What this process did: results of the inputs it committed, the inputs skipped, the mosaics."""

    results: list[PredictResult] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    #: inputs whose earlier outputs ``skip_existing`` recomputed → why they were not complete for this run
    recomputed: dict[str, str] = field(default_factory=dict)
    mosaics: dict[str, Path] = field(default_factory=dict)
    ranks: runtime.Torchrun = field(default_factory=runtime.Torchrun)

    def add(self, result: PredictResult, on_result: Callable[[PredictResult], None] | None) -> None:
        """Record an input's result as soon as it is committed (and hand it to ``on_result``)."""
        self.results.append(result)
        if on_result is not None:
            on_result(result)


#: A checkpoint path, a model already loaded with its metadata, or a :class:`~aerialmtl.inference.model.Predictor`
#: (a model loaded once with its settings, run on any number of inputs).
Checkpoint = str | Path | tuple[torch.nn.Module, ModelMeta] | Predictor


def predict_raster(ortho: str | Path, checkpoint: Checkpoint, out_dir: str | Path,
                   settings: PredictSettings | None = None, *, overwrite: bool = False, progress: bool = True,
                   checkpoint_name: str | None = None, **options: Any) -> PredictResult:
    """Predict height and land cover (with MC-dropout uncertainty) over a whole orthophoto.

    The one-input case of :func:`predict_many`.

    Args:
        ortho: orthophoto GeoTIFF (any size; read window by window), a URL or a GDAL path.
        checkpoint: checkpoint path, ``(model, meta)`` already loaded, or a
            :class:`~aerialmtl.inference.model.Predictor` (then with its own settings: pass neither ``settings``
            nor ``options``).
        out_dir: the prediction folder (see :mod:`aerialmtl.formats.prediction`).
        settings: predict's settings (:class:`~aerialmtl.inference.settings.PredictSettings`).
        overwrite: replace existing outputs instead of raising.
        progress: show progress bars.
        checkpoint_name: the checkpoint's name in ``prediction.json`` and messages (default: its path, or
            ``<in-memory model>``).
        options: the settings as keywords named like the fields of
            :class:`~aerialmtl.inference.settings.PredictSettings` (``mc=16, precision="fp32", aoi=...``), applied
            over ``settings``.

    Returns:
        A :class:`~aerialmtl.inference.job.PredictResult`.

    Raises:
        OutputExistsError: outputs exist and ``overwrite`` is false.
        InputError / AlignmentError / CheckpointError: unusable inputs (messages name the fix).
    """
    settings = _settings(checkpoint, settings, options, checkpoint_name)
    policy = _Policy(overwrite, False, progress, None, "out_dir")
    return _predict([ortho], checkpoint, out_dir, settings, policy, checkpoint_name).results[0]


def predict_many(
    orthos: Sequence[str | Path],
    checkpoint: Checkpoint,
    out: str | Path,
    settings: PredictSettings | None = None,
    *,
    overwrite: bool = False,
    skip_existing: bool = False,
    on_result: Callable[[PredictResult], None] | None = None,
    progress: bool = True,
    checkpoint_name: str | None = None,
    **options: Any,
) -> JobResult:
    """Predict every orthophoto of ``orthos``; see the module docstring.

    Args:
        orthos: the orthophotos.
        checkpoint: checkpoint path, ``(model, meta)`` or a :class:`~aerialmtl.inference.model.Predictor` (as
            for :func:`predict_raster`).
        out: prediction folder (one input) or parent folder (several).
        settings: predict's settings (:class:`~aerialmtl.inference.settings.PredictSettings`; the AOI applies
            to every input).
        overwrite: replace existing outputs.
        skip_existing: skip inputs whose prediction folder is complete.
        on_result: called with each input's result as soon as it is committed.
        progress: show progress bars (on rank 0 only).
        checkpoint_name: the checkpoint's name in ``prediction.json`` and messages (as for :func:`predict_raster`).
        options: the settings as keywords named like its fields (as for :func:`predict_raster`), applied over
            ``settings``.

    Returns:
        A :class:`JobResult` for this process.

    Raises:
        OutputExistsError: an input's outputs exist (neither ``overwrite`` nor ``skip_existing``).
        PeerFailure: an input failed on another rank (distributed runs).
    """
    settings = _settings(checkpoint, settings, options, checkpoint_name)
    return _predict(orthos, checkpoint, out, settings,
                    _Policy(overwrite, skip_existing, progress, on_result, "out"), checkpoint_name)


def _predict(orthos: Sequence[str | Path], checkpoint: Checkpoint, out: str | Path, settings: PredictSettings,
             policy: _Policy, checkpoint_name: str | None = None) -> JobResult:
    """Run :func:`predict_many` or :func:`predict_raster`.

    Load the model on this rank's device, read every input's header, hold the output folders, run.
    """
    ranks = runtime.Torchrun.from_env()
    targets = targets_for(orthos, out, policy.option)
    if isinstance(checkpoint, Predictor):
        predictor = checkpoint
    else:
        device = ranks.resolve_device(settings.device)
        predictor = Predictor(checkpoint, dataclasses.replace(settings, device=str(device)),
                              checkpoint_name=checkpoint_name)
    with runtime.gdal_env("predict"):
        for t in targets:  # every input usable before the first one takes time; each header read once
            t.src = predictor.open(t.ortho, warn=False)
        if predictor.settings.sun_tune:  # the tuned weights, before the engine is built from them
            predictor.tune([t.src for t in targets if t.src is not None])
    if not isinstance(checkpoint, Predictor):  # the engine chosen once, for this job (a cold cache weighed)
        predictor.fit_engine([t.src for t in targets if t.src is not None])
    ranks.join(predictor.device, runtime.SHARE_TIMEOUT)
    try:
        with contextlib.ExitStack() as held:
            _hold_folders(held, targets, Path(out), ranks, settings.aoi, policy.option)
            return _run(predictor, targets, Path(out), ranks, policy)
    finally:
        ranks.leave()


def _settings(checkpoint: Checkpoint, settings: PredictSettings | None, options: dict[str, Any],
              checkpoint_name: str | None = None) -> PredictSettings:
    """The run's settings: ``settings`` with ``options``, or a given :class:`Predictor`'s own.

    Raises:
        InputError: a :class:`Predictor` and settings or a name too (they would not apply to it).
    """
    if not isinstance(checkpoint, Predictor):
        return settings_of(settings, options)
    if settings is not None or options or checkpoint_name is not None:
        given = ("settings" if settings is not None else "checkpoint_name" if checkpoint_name is not None
                 else ", ".join(map(str, options)))
        raise InputError(f"a Predictor predicts with its own settings; pass them to Predictor(...) instead of "
                         f"here (got {given})")
    return checkpoint.settings


@dataclass(frozen=True)
class _Policy:
    """What :func:`predict_many` does with existing outputs, progress bars and results."""

    overwrite: bool
    skip_existing: bool
    progress: bool
    on_result: Callable[[PredictResult], None] | None
    option: str = "out"


def _hold_folders(held: contextlib.ExitStack, targets: Sequence[Target], out: Path, ranks: runtime.Torchrun,
                  aoi: str | Path | None, option: str) -> None:
    """Take the job's output folders on rank 0, for the whole job; every rank raises rank 0's error.

    The folders (:class:`~aerialmtl.io.outputs.OutputFolder`) are every input's prediction folder, and ``out`` with
    several inputs.
    """
    error: BaseException | None = None
    if ranks.rank == 0:
        try:
            for t in targets:  # an --out holding an input: refused (naming that input)
                check_not_input(out, {"ortho": t.ortho, "aoi": aoi}, option=option)
            folders = [out] if len(targets) > 1 else []
            for folder in [*folders, *(t.out for t in targets)]:
                held.enter_context(OutputFolder(folder, "predict", option=option, what="prediction folder"))
        except (AerialMTLError, OSError) as exc:
            error = exc
    errors = ranks.gather(error)  # also the barrier: no rank writes before rank 0 holds the folders
    if errors[0] is not None:
        raise errors[0]


def _job(predictor: Predictor, t: Target, overwrite: bool = False, option: str = "out") -> InputJob:
    """The job of target ``t`` (opened); ``option`` names its folder in messages."""
    assert t.src is not None
    return InputJob(predictor, t.src, t.out, overwrite=overwrite, option=option)


def _run(predictor: Predictor, targets: list[Target], out: Path, ranks: runtime.Torchrun,
         policy: _Policy) -> JobResult:
    """Run :func:`predict_many` once the folders are held.

    Choose the inputs, claim their outputs, plan the ranks' shares, compute and commit (one
    :class:`~aerialmtl.inference.job.InputJob` per input or strip), mosaic.
    """
    done = JobResult(ranks=ranks)
    todo, replace, kept = _select(predictor, targets, policy.skip_existing, done)
    if not policy.overwrite:  # once per input, before any work
        _claim(predictor, targets, out, todo, replace, kept, policy.option)
    if ranks.rank == 0:
        for k in todo:
            src = targets[k].src
            assert src is not None
            src.warn_resampled(predictor.meta)
            src.warn_unused_bands(predictor.meta)
    mine, shared = _shares(targets, todo, ranks)
    if ranks.rank == 0:  # hidden files of killed runs: removed before any rank writes
        for k in todo:
            _job(predictor, targets[k]).clean()
    ranks.gather(None)  # barrier
    with runtime.gdal_env("predict"):
        failures = _compute(predictor, targets, mine, shared, replace, ranks, policy,
                            lambda res: done.add(res, policy.on_result))
    if failures:
        if ranks.rank == 0:  # strips of failed inputs: hidden files only, final paths untouched
            for t in targets:
                if str(t.ortho) in {f[0] for f in failures} and t.out.is_dir():
                    _job(predictor, t).clean()
        ortho, rank, message = failures[0]
        more = f" ({len(failures) - 1} more input(s) failed too)" if len(failures) > 1 else ""
        raise PeerFailure(
            f"rank {rank} failed on input '{ortho}': {message}{more}; the other inputs are complete: fix it and "
            "re-run with ‹skip_existing=True› to finish"
        )
    if len(targets) > 1 and ranks.rank == 0:
        done.mosaics = write_mosaics(predictor, targets, out)
    ranks.gather(None)  # nobody leaves before the mosaics exist
    return done


def _select(predictor: Predictor, targets: Sequence[Target], skip_existing: bool,
            done: JobResult) -> tuple[list[int], set[int], dict[int, str]]:
    """The inputs to compute, those ``skip_existing`` recomputes, and why it kept the others' files.

    Recomputed: those whose earlier, outdated outputs ``skip_existing`` replaces (their ``prediction.json`` proves
    every output there is that run's); kept: why ``skip_existing`` neither skipped nor may replace the others' files
    (no readable ``prediction.json`` owns them). The skipped ones go into ``done``.
    """
    todo = []
    replace: set[int] = set()
    kept: dict[int, str] = {}
    files = folder_files(s.name for s in predictor.layers)  # layers, styles, item.json, prediction.json
    for k, t in enumerate(targets):
        if skip_existing:
            assert t.src is not None
            folder = PredictionFolder(t.out)
            reason = folder.check(predictor.provenance(t.src))
            if reason is None:
                done.skipped.append(t.ortho)
                continue
            owned = set(folder.owned_files())
            if owned:  # an earlier run's outputs (its prediction.json lists them): recomputed, and said so
                done.recomputed[t.ortho] = reason
                if all(f in owned for f in files if (t.out / f).exists()):
                    replace.add(k)
            else:
                kept[k] = reason
        todo.append(k)
    return todo, replace, kept


def _claim(predictor: Predictor, targets: Sequence[Target], out: Path, todo: Sequence[int],
           replace: set[int], kept: Mapping[int, str], option: str) -> None:
    """Refuse existing outputs (without ``overwrite``).

    Each input's, and with several inputs the mosaics and ``collection.json`` (a user's own are never replaced
    silently); ``kept``: why ``skip_existing`` could not use an input's folder, said with the refusal.
    """
    for k in todo:
        if k not in replace:
            try:
                _job(predictor, targets[k], option=option).claim()
            except OutputExistsError as exc:
                if k not in kept:
                    raise
                raise OutputExistsError(f"{exc.message} (‹skip_existing› could not tell them finished: {kept[k]})",
                                        param=exc.param) from None
    if len(targets) > 1:
        owned = set(collection_files(out))
        prediction_folder(out, option).claim(
            [f for f in mosaic_files(s.name for s in predictor.layers) if f not in owned], overwrite=False)


def _shares(targets: Sequence[Target], todo: Sequence[int], ranks: runtime.Torchrun) -> tuple[list[Share], set[int]]:
    """This rank's shares (:func:`partition` of the inputs' window rows), and the inputs cut between ranks."""
    plans: list[Plan] = []
    for k in todo:
        plan = targets[k].plan
        assert plan is not None, "the inputs to do are open"
        plans.append(plan)
    costs = [[float(len(p.cols.starts) * p.rows.size * p.cols.size)] * len(p.window_rows) for p in plans]
    shares = partition(costs, ranks.world)
    mine = [Share(todo[s.target], s.start, s.stop) for s in shares[ranks.rank]]
    shared = {todo[s.target] for r in shares for s in r if s.start > 0 or s.stop < len(plans[s.target].window_rows)}
    return mine, shared


def _compute(predictor: Predictor, targets: Sequence[Target], mine: Sequence[Share], shared: set[int],
             replace: set[int], ranks: runtime.Torchrun, policy: _Policy,
             committed: Callable[[PredictResult], None]) -> list[tuple[str, int, str]]:
    """Compute this rank's shares and commit what it owns; ``committed`` gets each result.

    A whole input at once, a shared one (its first strip here) once every rank's strips are in.

    Returns:
        every rank's failures, ``(input, rank, message)`` (in one process the first failure is raised instead).
    """
    failures: list[tuple[str, int, str]] = []
    strips: dict[int, StripResult] = {}
    committers: dict[int, InputJob] = {}  # shared inputs this rank commits: the job of their first strip
    commits = Commits(committed, raise_failures=ranks.world == 1, in_thread=commits_in_thread(predictor.device))

    def settle() -> None:  # the commit in flight; with ranks, its failure is this rank's
        failure = commits.settle()
        if failure is not None:
            failures.append((failure[0], ranks.rank, failure[1]))

    try:
        for share in mine:
            t = targets[share.target]
            assert t.src is not None
            whole = share.target not in shared
            started = time.perf_counter()
            job = _job(predictor, t, policy.overwrite or share.target in replace)
            try:
                strip = job.strip(None if whole else (share.start, share.stop), check_outputs=False,
                                  progress=policy.progress and ranks.rank == 0)
            except Exception as exc:
                if ranks.world == 1:
                    raise
                failures.append((str(t.ortho), ranks.rank, one_line(exc)))
                continue
            if not whole:
                strips[share.target] = strip
                if share.start == 0:
                    committers[share.target] = job  # this rank joins the strips
                continue
            try:  # the previous input's commit ran beside this strip
                settle()
            except BaseException:
                job.abort()  # one process stops at the first failure: this strip's files go too
                raise
            commits.start(job, strip, started, str(t.ortho))  # the one-strip case: no other rank's strips to wait for
            if not commits.in_thread:
                settle()
        settle()
    finally:
        commits.close()

    # every rank's strips and failures; then the first strip's rank commits each shared input
    gathered = ranks.gather((strips, failures))
    all_failures = [f for _, fs in gathered for f in fs]
    failed = {f[0] for f in all_failures}
    for k, job in committers.items():
        t = targets[k]
        first = strips[k]
        others = [res for st, _ in gathered for kk, res in st.items() if kk == k and res.row_start != first.row_start]
        if str(t.ortho) in failed:
            job.abort()  # its writer's files and the input's leftovers
            continue
        try:
            res = job.commit([first, *others], processes=1 + len(others))
        except Exception as exc:
            failures.append((str(t.ortho), ranks.rank, one_line(exc)))
            all_failures.append(failures[-1])
            continue
        committed(res)
    if ranks.world > 1:
        all_failures = [f for fs in ranks.gather(failures) for f in fs]
    return all_failures


def write_mosaics(predictor: Predictor, targets: Sequence[Target], out: Path) -> dict[str, Path]:
    """One VRT per layer over every input's folder, and the STAC collection.

    Each mosaic (:func:`~aerialmtl.formats.prediction.mosaic_filename`) has its QGIS style; ``collection.json``
    links the inputs' items and the mosaics.

    A mosaic an earlier run here wrote (its ``collection.json`` lists it) of a layer this run does not make
    (e.g. ``height_std`` after ``--mc 1``) is removed with its style: it would point at layers that are gone.
    """
    mosaics, styles = {}, {}
    earlier = set(collection_files(out))
    made = {spec.name for spec in predictor.layers}
    for name in LAYERS:
        if name not in made:
            for stale in (mosaic_filename(name), mosaic_style_filename(name)):
                if stale in earlier:
                    (out / stale).unlink(missing_ok=True)
    for spec in predictor.layers:
        sources = [t.out / spec.filename for t in targets if (t.out / spec.filename).is_file()]
        if sources:
            mosaics[spec.name] = mosaic_vrt(out / mosaic_filename(spec.name), sources, categorical=spec.categorical)
            styles[spec.name] = write_raster_style(mosaics[spec.name], spec)
    write_collection(out, [t.out for t in targets], mosaics, styles)
    return mosaics


__all__ = ["Checkpoint", "JobResult", "Share", "Target", "partition", "predict_many", "predict_raster", "targets_for",
           "write_mosaics"]
