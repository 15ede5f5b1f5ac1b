"""Model configuration of the multi-task D3-Net (saved inside every checkpoint)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from aerialmtl.errors import ConfigError

Task = Literal["height", "classes"]


@dataclass(frozen=True)
class ModelConfig:
    """D3-Net hyper-parameters. The defaults are the paper's (DenseNet-121 encoder, p = 0.5).

    Attributes:
        in_channels: number of input image bands.
        tasks: enabled task heads; ``height`` (1 channel, metres) and/or ``classes`` (K logits).
        num_classes: K, the number of land-cover classes (ignored without the ``classes`` task).
        growth_rate: DenseNet growth rate k.
        block_config: dense layers per dense block (DenseNet-121: 6-12-24-16).
        num_init_features: channels after the stem.
        bn_size: bottleneck width multiplier (1×1 conv outputs ``bn_size * growth_rate``).
        compression: transition channel compression.
        dropout: dropout probability in the deepest shared decoder blocks (MC dropout at test time).
        dropout_blocks: how many of the deepest shared decoder blocks carry dropout (after each of
            their two BatchNorms). The authors' implementation puts it in the two deepest blocks.
        task_blocks: decoder up-blocks owned by each task (the paper: 2), before its 3×3 output conv.
        encoder_weights: optional path of a local torchvision-format DenseNet-121 state dict.
    """

    in_channels: int = 3
    tasks: tuple[Task, ...] = ("height", "classes")
    num_classes: int = 20
    growth_rate: int = 32
    block_config: tuple[int, ...] = (6, 12, 24, 16)
    num_init_features: int = 64
    bn_size: int = 4
    compression: float = 0.5
    dropout: float = 0.5
    dropout_blocks: int = 2
    task_blocks: int = 2
    encoder_weights: str | None = None

    def __post_init__(self) -> None:
        if self.in_channels < 1:
            raise ConfigError(f"model.in_channels: must be ≥ 1, got {self.in_channels}")
        if not self.tasks:
            raise ConfigError("model.tasks: enable at least one of 'height', 'classes'")
        if len(set(self.tasks)) != len(self.tasks):
            raise ConfigError(f"model.tasks: duplicate entries in {list(self.tasks)}")
        if "classes" in self.tasks and self.num_classes < 2:
            raise ConfigError(f"model.num_classes: must be ≥ 2 with the 'classes' task, got {self.num_classes}")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"model.dropout: must be in [0, 1), got {self.dropout}")
        if len(self.block_config) != 4:
            raise ConfigError(f"model.block_config: expected 4 dense blocks, got {list(self.block_config)}")
        if not 1 <= self.task_blocks <= 4:
            raise ConfigError(f"model.task_blocks: must be in 1..4, got {self.task_blocks}")
        if not 0 <= self.dropout_blocks <= 5 - self.task_blocks:
            raise ConfigError(
                f"model.dropout_blocks: must be in 0..{5 - self.task_blocks} (the shared decoder blocks), "
                f"got {self.dropout_blocks}"
            )
