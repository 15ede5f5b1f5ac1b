"""``log.csv`` of a training run: one ``train`` row every ``schedule.log_every`` steps, one ``val`` row per
validation (columns :data:`LOG_COLUMNS`; empty cells where a value does not apply)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from aerialmtl.io.oserrors import writing

LOG_COLUMNS = (
    "kind", "step", "epoch", "time_s", "lr", "loss", "loss_height", "loss_classes",
    "val_loss_height", "val_loss_classes", "height_mae", "height_rmse", "oa", "miou", "score",
)


class CsvLog:
    """Append rows to ``path`` (a new file gets the header; ``append`` keeps an existing one)."""

    def __init__(self, path: Path, append: bool) -> None:
        self.path = path
        if not (append and path.is_file()):
            with writing(path, "the training log"), path.open("w", newline="") as fh:
                csv.writer(fh).writerow(LOG_COLUMNS)

    def write(self, **row: Any) -> None:
        """Append one row (a full disk or a lost permission: an OutputError naming the file)."""
        with writing(self.path, "the training log"), self.path.open("a", newline="") as fh:
            csv.writer(fh).writerow(["" if row.get(c) is None else row.get(c) for c in LOG_COLUMNS])


__all__ = ["LOG_COLUMNS", "CsvLog"]
