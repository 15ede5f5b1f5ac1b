"""``log.csv`` of a training run; the format is owned by :mod:`aerialmtl.formats.run` (re-exported here)."""

from __future__ import annotations

from aerialmtl.formats.run import LOG_COLUMNS, CsvLog

__all__ = ["LOG_COLUMNS", "CsvLog"]
