"""The encoders a D3-Net can have, one registry entry each (as segmentation_models_pytorch assembles models).

An entry says everything the rest of the package needs to know about an encoder:

* ``build(settings)`` — the encoder module for a model configuration (its ``in_channels`` and, for the
  DenseNet, its growth rate and blocks). Every encoder maps a B×C×H×W image (H, W multiples of 32) to the
  list of its stride 2, 4, 8, 16 and 32 features, highest resolution first, and has ``out_channels``
  (their channel counts, in that order): the one decoder of :class:`~aerialmtl.models.d3net.D3Net` takes them.
* ``load_weights(encoder, weights)`` — copies pretrained weights (a local file, or ``imagenet`` where
  ``imagenet`` is true) into a built encoder (:mod:`aerialmtl.models.pretrained`).
* ``input_scaling`` — the per-band ``(mean, std)`` of 8-bit inputs the pretrained weights were trained
  with, or ``None`` where the tile folder's statistics normalise the inputs.

Adding an encoder is one entry in :data:`ENCODERS` (and its module); the tests that loop over the registry
(forward and backward of every encoder, every encoder on every engine) then cover it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from torch import nn

from aerialmtl.models.densenet import DenseNetEncoder
from aerialmtl.models.efficientnet import IMAGENET_LITE_MEAN, IMAGENET_LITE_STD, VARIANTS, EfficientNetLiteEncoder
from aerialmtl.models.pretrained import load_efficientnet_lite, load_torchvision_densenet


class EncoderSettings(Protocol):
    """The part of a model configuration an encoder is built from (:class:`~aerialmtl.models.config.ModelConfig`)."""

    @property
    def in_channels(self) -> int:
        """Input bands."""

    @property
    def growth_rate(self) -> int:
        """DenseNet growth rate."""

    @property
    def block_config(self) -> tuple[int, ...]:
        """DenseNet layers per dense block."""

    @property
    def num_init_features(self) -> int:
        """DenseNet stem width."""

    @property
    def bn_size(self) -> int:
        """DenseNet bottleneck factor."""

    @property
    def compression(self) -> float:
        """DenseNet transition compression."""


@dataclass(frozen=True)
class EncoderSpec:
    """One encoder of the registry (see the module docstring).

    Attributes:
        name: the ``model.encoder`` value that selects it.
        build: settings → the encoder module (with ``out_channels``).
        load_weights: (built encoder, weights path or ``"imagenet"``) → None; copies them in place.
        imagenet: whether ``encoder_weights: imagenet`` is available (from installed packages).
        input_scaling: ``(mean, std)`` per band for 8-bit inputs with pretrained weights; ``None``: the
            tile folder's statistics.
    """

    name: str
    build: Callable[[EncoderSettings], nn.Module]
    load_weights: Callable[[nn.Module, str | Path], object]
    imagenet: bool = False
    input_scaling: tuple[float, float] | None = None


def _densenet(settings: EncoderSettings) -> nn.Module:
    return DenseNetEncoder(in_channels=settings.in_channels, growth_rate=settings.growth_rate,
                           block_config=settings.block_config, num_init_features=settings.num_init_features,
                           bn_size=settings.bn_size, compression=settings.compression)


def _load_densenet(encoder: nn.Module, weights: str | Path) -> object:
    assert isinstance(encoder, DenseNetEncoder)
    return load_torchvision_densenet(encoder, weights)


def _lite(variant: str) -> Callable[[EncoderSettings], nn.Module]:
    def build(settings: EncoderSettings) -> nn.Module:
        return EfficientNetLiteEncoder(variant, settings.in_channels)

    return build


def _load_lite(encoder: nn.Module, weights: str | Path) -> object:
    return load_efficientnet_lite(encoder, weights)


#: Name → encoder; ``densenet121`` (the paper's) first, the default.
ENCODERS: dict[str, EncoderSpec] = {
    "densenet121": EncoderSpec("densenet121", _densenet, _load_densenet),
    **{name: EncoderSpec(name, _lite(name), _load_lite, imagenet=True,
                     input_scaling=(IMAGENET_LITE_MEAN, IMAGENET_LITE_STD)) for name in VARIANTS},
}


def feature_channels(encoder: nn.Module) -> tuple[int, ...]:
    """The channel counts of ``encoder``'s stride 2, 4, 8, 16 and 32 features (its ``out_channels``)."""
    channels = tuple(int(c) for c in getattr(encoder, "out_channels"))  # noqa: B009 - nn.Module's __getattr__
    if len(channels) != 5:
        raise ValueError(f"{type(encoder).__name__}.out_channels must list the 5 stride 2–32 feature widths, "
                         f"got {channels}")
    return channels


def encoder_spec(name: str) -> EncoderSpec:
    """The registry entry of encoder ``name``.

    Raises:
        KeyError: no such encoder (the model configuration checks names first, with its own message).
    """
    return ENCODERS[name]


__all__ = ["ENCODERS", "EncoderSettings", "EncoderSpec", "encoder_spec", "feature_channels"]
