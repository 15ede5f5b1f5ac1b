"""The run folder of ``aerialmtl train``: what training writes and ``predict``, ``--resume`` and ``--init`` read.

::

    RUN/config.yaml   the resolved training config (model fields filled from dataset.yaml, absolute data dir);
                      ``--resume`` reads it unless ``--config`` is given
    RUN/last.pt       checkpoint after every validation and when training stops, with the resume state
                      (``train_state``: :data:`RESUME_KEYS`)
    RUN/best.pt       checkpoint with the best validation score so far (what predict should use)
    RUN/log.csv       one ``train`` row every ``schedule.log_every`` steps, one ``val`` row per validation
                      (columns :data:`LOG_COLUMNS`; empty cells where a value does not apply)

Checkpoints are written by :func:`aerialmtl.formats.checkpoint.save_checkpoint` (staging file, then an
atomic rename), ``config.yaml`` through :func:`aerialmtl.io.outputs.write_text_atomic`; a run holds the
folder's lock (:class:`aerialmtl.io.outputs.OutputFolder`) for its whole length, so two runs never write
one folder. ``--overwrite`` replaces exactly these four files (:data:`RUN_FILES`); other files in the
folder are left alone.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from aerialmtl.io.oserrors import writing
from aerialmtl.io.outputs import write_text_atomic

CONFIG_YAML = "config.yaml"
LAST_PT = "last.pt"
BEST_PT = "best.pt"
LOG_CSV = "log.csv"
#: Every file a run writes, in the order a listing shows them.
RUN_FILES = (LAST_PT, BEST_PT, LOG_CSV, CONFIG_YAML)

#: Columns of ``log.csv``.
LOG_COLUMNS = (
    "kind", "step", "epoch", "time_s", "lr", "loss", "loss_height", "loss_classes",
    "val_loss_height", "val_loss_classes", "height_mae", "height_rmse", "oa", "miou", "score",
)

#: Keys of a checkpoint's ``train_state`` (the resume state; ``rng_ranks``, ``world_size`` and
#: ``global_batch`` are missing from checkpoints of older versions). Counters and the best score are
#: :meth:`aerialmtl.training.state.TrainState.to_dict`.
RESUME_KEYS = ("optimizer", "weighting", "rng", "rng_ranks", "world_size", "global_batch", "config")
#: Also in ``train_state`` of a run with ``optim.ema``: the trained weights (the checkpoint's are their average)
RAW_WEIGHTS_KEY = "raw_weights"


@dataclass(frozen=True)
class RunFolder:
    """A run folder on disk.

    Attributes:
        path: the folder.
    """

    path: Path

    def __init__(self, path: str | Path) -> None:
        object.__setattr__(self, "path", Path(path))

    @property
    def config(self) -> Path:
        """The run's resolved ``config.yaml``."""
        return self.path / CONFIG_YAML

    @property
    def last(self) -> Path:
        """The run's ``last.pt`` (what ``resume`` continues)."""
        return self.path / LAST_PT

    @property
    def best(self) -> Path:
        """The run's ``best.pt`` (what predict should use)."""
        return self.path / BEST_PT

    @property
    def log(self) -> Path:
        """The run's ``log.csv``."""
        return self.path / LOG_CSV

    def paths(self) -> dict[str, Path]:
        """File name → path, for every file of :data:`RUN_FILES`."""
        return {name: self.path / name for name in RUN_FILES}

    def can_resume(self) -> bool:
        """Whether a run to continue is there (``last.pt`` exists)."""
        return self.last.is_file()

    def write_config(self, resolved: dict[str, Any]) -> Path:
        """Write ``config.yaml`` (atomically)."""
        return write_text_atomic(self.config, yaml.safe_dump(resolved, sort_keys=False))


class CsvLog:
    """Append rows to ``log.csv`` at ``path`` (a new file gets the header; ``append`` keeps an existing one)."""

    def __init__(self, path: Path, append: bool) -> None:
        self.path = path
        if not (append and path.is_file()):
            buf = io.StringIO(newline="")
            csv.writer(buf).writerow(LOG_COLUMNS)
            with writing(path, "the training log"):
                write_text_atomic(path, buf.getvalue())

    def write(self, **row: Any) -> None:
        """Append one row (a full disk or a lost permission: an OutputError naming the file)."""
        with writing(self.path, "the training log"), self.path.open("a", newline="") as fh:
            csv.writer(fh).writerow(["" if row.get(c) is None else row.get(c) for c in LOG_COLUMNS])


__all__ = ["BEST_PT", "CONFIG_YAML", "LAST_PT", "LOG_COLUMNS", "LOG_CSV", "RAW_WEIGHTS_KEY", "RESUME_KEYS",
           "RUN_FILES", "CsvLog", "RunFolder"]
