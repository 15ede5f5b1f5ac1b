"""aerialmtl: height (nDSM) and land-cover maps with MC-dropout uncertainty from aerial orthophotos.

The method is the multi-task D3-Net of Carvalho et al., "Multi-task learning of height and semantics
from aerial images", IEEE GRSL 2019.

The public API, one name per step of the workflow (each imported on first use, so ``import aerialmtl``
stays light)::

    from aerialmtl import tile_dataset, load_train_config, train, predict_raster, evaluate_prediction

    tile_dataset("ortho.tif", "tiles/", dsm="dsm.tif", dtm="dtm.tif")
    result = train(load_train_config("configs/d3net_small_synth.yaml"), "tiles/", "runs/a")
    predict_raster("new_area.tif", result.best_checkpoint, "maps/new_area", mc=30)
    evaluate_prediction("maps/new_area", height_ref="ndsm_ref.tif", out="report.json")
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from aerialmtl._version import __version__

#: Public name → the module that defines it.
_EXPORTS: dict[str, str] = {
    # data preparation
    "synthesize": "aerialmtl.data.synth",
    "tile_dataset": "aerialmtl.tiling.tile",
    "TileOptions": "aerialmtl.tiling.tile",
    "SplitSpec": "aerialmtl.tiling.splits",
    "NdsmOptions": "aerialmtl.io.align",
    "ClassScheme": "aerialmtl.classes",
    "reference_grid": "aerialmtl.io.align",
    "Grid": "aerialmtl.io.align",
    # training
    "TrainConfig": "aerialmtl.training.config",
    "load_train_config": "aerialmtl.training.config",
    "train": "aerialmtl.training.loop",
    "TrainResult": "aerialmtl.training.trainer",
    # models and checkpoints
    "ModelConfig": "aerialmtl.models.config",
    "D3Net": "aerialmtl.models.d3net",
    "mc_predict": "aerialmtl.models.mc_dropout",
    "ModelMeta": "aerialmtl.formats.checkpoint",
    "load_checkpoint": "aerialmtl.formats.checkpoint",
    "load_model": "aerialmtl.formats.checkpoint",
    "save_checkpoint": "aerialmtl.formats.checkpoint",
    # mapping
    "Predictor": "aerialmtl.inference.predict",
    "predict_raster": "aerialmtl.inference.predict",
    "predict_many": "aerialmtl.inference.predict",
    "PredictSettings": "aerialmtl.inference.predict",
    "PredictResult": "aerialmtl.inference.job",
    "PredictionFolder": "aerialmtl.formats.prediction",
    "extract_buildings": "aerialmtl.buildings",
    "write_buildings": "aerialmtl.buildings",
    # evaluation
    "evaluate_prediction": "aerialmtl.evaluation.evaluate",
    "EvaluateOptions": "aerialmtl.evaluation.evaluate",
    # errors
    "AerialMTLError": "aerialmtl.errors",
    "InputError": "aerialmtl.errors",
    "ConfigError": "aerialmtl.errors",
    "CheckpointError": "aerialmtl.errors",
    "OutputExistsError": "aerialmtl.errors",
}

__all__ = [
    "__version__",
    "synthesize",
    "tile_dataset",
    "TileOptions",
    "SplitSpec",
    "NdsmOptions",
    "ClassScheme",
    "reference_grid",
    "Grid",
    "TrainConfig",
    "load_train_config",
    "train",
    "TrainResult",
    "ModelConfig",
    "D3Net",
    "mc_predict",
    "ModelMeta",
    "load_checkpoint",
    "load_model",
    "save_checkpoint",
    "Predictor",
    "predict_raster",
    "predict_many",
    "PredictSettings",
    "PredictResult",
    "PredictionFolder",
    "extract_buildings",
    "write_buildings",
    "evaluate_prediction",
    "EvaluateOptions",
    "AerialMTLError",
    "InputError",
    "ConfigError",
    "CheckpointError",
    "OutputExistsError",
]


def __getattr__(name: str) -> Any:
    """Import a public name from its module on first use (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'aerialmtl' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from aerialmtl.buildings import extract_buildings, write_buildings
    from aerialmtl.classes import ClassScheme
    from aerialmtl.data.synth import synthesize
    from aerialmtl.errors import AerialMTLError, CheckpointError, ConfigError, InputError, OutputExistsError
    from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction
    from aerialmtl.formats.checkpoint import ModelMeta, load_checkpoint, load_model, save_checkpoint
    from aerialmtl.formats.prediction import PredictionFolder
    from aerialmtl.inference.job import PredictResult
    from aerialmtl.inference.predict import Predictor, PredictSettings, predict_many, predict_raster
    from aerialmtl.io.align import Grid, NdsmOptions, reference_grid
    from aerialmtl.models.config import ModelConfig
    from aerialmtl.models.d3net import D3Net
    from aerialmtl.models.mc_dropout import mc_predict
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import TileOptions, tile_dataset
    from aerialmtl.training.config import TrainConfig, load_train_config
    from aerialmtl.training.loop import train
    from aerialmtl.training.trainer import TrainResult
