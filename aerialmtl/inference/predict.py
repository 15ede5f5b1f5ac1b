"""``predict`` from Python: the one-call forms and what they are made of, in one place.

* :func:`predict_raster` — one orthophoto into one prediction folder;
* :func:`predict_many` — many, in one process or many under ``torchrun`` (:mod:`aerialmtl.inference.jobs`);
* :class:`PredictSettings` — predict's settings, one frozen, validated object
  (:mod:`aerialmtl.inference.settings`);
* :class:`Predictor` — the model loaded once with its settings (:mod:`aerialmtl.inference.model`).

The inference package's layers run jobs → job → model → runner → engines → reader/stitch/writer (an
import-linter contract, pyproject.toml); this module sits above them all and only names them.
"""

from __future__ import annotations

from aerialmtl.inference.job import PredictResult
from aerialmtl.inference.jobs import JobResult, predict_many, predict_raster
from aerialmtl.inference.model import DEFAULT_MC_SAMPLES, Predictor
from aerialmtl.inference.settings import PredictSettings

__all__ = ["DEFAULT_MC_SAMPLES", "JobResult", "PredictResult", "PredictSettings", "Predictor",
           "predict_many", "predict_raster"]
