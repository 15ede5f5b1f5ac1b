"""The run folder of a training command (``train``, ``pretrain``): one policy, checked and taken one way.

A command describes its folder once (:class:`RunFolderPolicy`: the files a run of it writes, the files it
stages besides them, and the files of others it refuses to replace); :meth:`RunFolderPolicy.check` judges a
folder before anything is written and :meth:`RunFolderPolicy.take` takes it (its lock, held until the run
ends), clears a replaced run and checks again under the lock. The rules are the same for every command:

* ``resume`` with ``overwrite`` (or with ``init``) is refused, naming both options;
* a file where the folder should be is refused; another process writing there is named first;
* ``resume`` needs the folder's ``last.pt``;
* a new run refuses a folder that holds any of its run files unless ``overwrite``, which replaces only
  those files (never others).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.formats.run import LAST_PT, RUN_FILES
from aerialmtl.io.outputs import FolderLock, OutputFolder, is_job_leader


@dataclass(frozen=True)
class RunFolderPolicy:
    """How a training command treats its run folder (see the module docstring).

    Attributes:
        command: the command writing it (``"train"``, ``"pretrain"``): the lock's name.
        files: the files a run of it writes; ``overwrite`` replaces them, and a new run refuses a folder
            holding any of them otherwise.
        staged: further files it writes atomically (a killed run's staging files of them are removed).
        guard: the command's own refusals (``run folder → None``, raising), e.g. files of another command it
            never replaces; called before the files are judged, and again under the lock.
    """

    command: str
    files: tuple[str, ...]
    staged: tuple[str, ...] = ()
    guard: Callable[[Path], None] | None = None

    def check(self, out_dir: str | Path, *, resume: bool = False, overwrite: bool = False,
              init: str | Path | None = None) -> None:
        """Judge the folder before anything is written (every process calls it).

        Raises:
            InputError: ``out_dir`` is a file; ``resume`` without ``last.pt``; ``resume`` with ``overwrite`` or
                ``init`` (``param`` names both options: ``"resume/overwrite"``, ``"resume/init"``).
            OutputExistsError: a run's files exist and neither ``resume`` nor ``overwrite`` is given (or the
                guard's refusal).
            OutputInUseError: another process holds the folder's lock.
        """
        run = Path(out_dir)
        if resume and overwrite:
            raise InputError("‹resume› continues a run and ‹overwrite› replaces it; pass only one",
                             param="resume/overwrite")
        if resume and init is not None:
            raise InputError("‹resume› continues the run's own weights; ‹init› starts a new run from a checkpoint; "
                             "pass only one", param="resume/init")
        if run.exists() and not run.is_dir():
            raise InputError(f"‹out_dir› '{run}' is a file; pass a folder", param="out_dir")
        if run.is_dir() and is_job_leader():  # another run writing there: say so before judging its files
            FolderLock(run, self.command).check_free()
        self._check_files(run, resume, overwrite)

    def _check_files(self, run: Path, resume: bool, overwrite: bool) -> None:
        if resume and not (run / LAST_PT).is_file():
            raise InputError(f"‹resume› '{run / LAST_PT}' does not exist; there is no run to resume there",
                             param="resume")
        if self.guard is not None:
            self.guard(run)
        existing = [n for n in self.files if (run / n).exists()]
        if existing and not resume and not overwrite:
            raise OutputExistsError(
                f"run folder '{run}' already holds {', '.join(existing)}; pass ‹resume=True› to continue it, "
                "‹overwrite=True› to replace the run, or another ‹out_dir›")

    def take(self, folder: OutputFolder, stack: contextlib.ExitStack, *, resume: bool = False,
             overwrite: bool = False) -> None:
        """Take the folder (its lock, held until ``stack`` closes) and prepare it for the run.

        Removes a killed run's staging files of :attr:`files` and :attr:`staged`; for a new run with
        ``overwrite``, the previous run's :attr:`files` (never others); then judges the files again under the
        lock (what is there now is final). Rank 0 only under torchrun.
        """
        stack.enter_context(folder)
        folder.remove_leftovers(self.files + self.staged)
        if overwrite and not resume:
            folder.remove_owned(self.files)
        self._check_files(folder.path, resume, overwrite)


#: The run folder of ``aerialmtl train``: ``last.pt``, ``best.pt``, ``log.csv``, ``config.yaml``.
TRAIN_FOLDER = RunFolderPolicy("train", RUN_FILES)


def check_run_folder(out_dir: str | Path, resume: bool = False, overwrite: bool = False,
                     init: str | Path | None = None) -> None:
    """The run-folder policy of ``aerialmtl train`` (:data:`TRAIN_FOLDER`), checked before anything is written.

    Raises:
        InputError: ``out_dir`` is a file; ``resume`` without ``last.pt``; ``resume`` with ``overwrite`` or
            ``init`` (``param`` names the option pair). The one check of these pairs: the CLI and
            :func:`~aerialmtl.training.setup.prepare_training` rely on it.
        OutputExistsError: a run's files exist and neither ``resume`` nor ``overwrite`` is given.
        OutputInUseError: another process holds the folder's lock.
    """
    TRAIN_FOLDER.check(out_dir, resume=resume, overwrite=overwrite, init=init)


__all__ = ["TRAIN_FOLDER", "RunFolderPolicy", "check_run_folder"]
