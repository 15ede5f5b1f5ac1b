"""DenseNet-BC encoder with the D3-Net stem, in plain torch (no torchvision).

Structure (Huang et al. 2017, DenseNet-BC), as used by D3-Net (Carvalho et al. 2018/2019):

* stem: ``conv0`` 3×3 stride 2 (pad 1) → ``norm0`` → LeakyReLU(0.2) → ``downconv0`` 4×4 stride 2 (pad 1)
  → ``norm1`` → LeakyReLU(0.2); no max-pool. The output of the first activation (stride 2) is the
  highest-resolution skip. (The authors' implementation uses LeakyReLU(0.2) in the stem and after
  ``norm5``; we follow it.)
* dense layer: BN → ReLU → conv1×1 (``bn_size·k`` channels) → BN → ReLU → conv3×3 (``k`` channels),
  its output concatenated to its input.
* transition: BN → ReLU → conv1×1 (``compression`` × channels); its PRE-POOL output is a skip, then
  avg-pool 2×2.
* after the last dense block: ``norm5`` → LeakyReLU(0.2).

Module names follow torchvision (``features.conv0``, ``features.denseblock1.denselayer1.norm1``,
``features.transition1.conv``, ``features.norm5``...) so that ImageNet weights map by name (see
:mod:`aerialmtl.models.pretrained`); only the stem (``conv0`` is 3×3 here, 7×7 there, and
``downconv0``/``norm1`` do not exist there) differs.

Output strides of the returned features: 2, 4, 8, 16, 32 (highest resolution first).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn


class DenseLayer(nn.Module):
    """BN-ReLU-conv1×1-BN-ReLU-conv3×3 producing ``growth_rate`` new channels.

    ``forward`` returns only the NEW features (B×k×H×W); the block does the concatenation.
    """

    def __init__(self, in_channels: int, growth_rate: int, bn_size: int) -> None:
        super().__init__()
        self.norm1 = nn.BatchNorm2d(in_channels)
        self.relu1 = nn.ReLU(inplace=True)
        self.conv1 = nn.Conv2d(in_channels, bn_size * growth_rate, kernel_size=1, bias=False)
        self.norm2 = nn.BatchNorm2d(bn_size * growth_rate)
        self.relu2 = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(bn_size * growth_rate, growth_rate, kernel_size=3, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) → (B, growth_rate, H, W) new features of the layer."""
        out = self.conv1(self.relu1(self.norm1(x)))
        result: torch.Tensor = self.conv2(self.relu2(self.norm2(out)))
        return result


class DenseBlock(nn.ModuleDict):
    """``num_layers`` dense layers; input B×C×H×W → output B×(C + num_layers·k)×H×W.

    With autograd recording, each layer's output is concatenated to the running tensor (one copy of
    the running features per layer, as in torchvision). Without autograd (inference), the block
    allocates its output once and every layer writes its ``k`` new channels into it, reading a channel
    view of the features before it: no re-concatenation.
    """

    def __init__(self, num_layers: int, in_channels: int, growth_rate: int, bn_size: int) -> None:
        super().__init__()
        for i in range(num_layers):
            self[f"denselayer{i + 1}"] = DenseLayer(in_channels + i * growth_rate, growth_rate, bn_size)
        self.in_channels = in_channels
        self.out_channels = in_channels + num_layers * growth_rate
        self.growth_rate = growth_rate

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) → (B, out_channels, H, W): the input with every layer's features appended."""
        layers = list(self.values())
        if not layers:
            return x
        if torch.is_grad_enabled():
            for layer in layers:
                x = torch.cat([x, layer(x)], 1)
            return x
        # Inference: one output buffer, layers write their slice in place.
        new = layers[0](x)
        memory_format = (torch.channels_last if x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last)
                         and not x.is_contiguous() else torch.contiguous_format)
        buf = torch.empty((x.shape[0], self.out_channels, x.shape[2], x.shape[3]), dtype=new.dtype,
                          device=x.device).contiguous(memory_format=memory_format)
        c = self.in_channels
        buf[:, :c].copy_(x)
        buf[:, c:c + self.growth_rate].copy_(new)
        c += self.growth_rate
        for layer in layers[1:]:
            buf[:, c:c + self.growth_rate].copy_(layer(buf[:, :c]))
            c += self.growth_rate
        return buf


class Transition(nn.Module):
    """BN → ReLU → conv1×1; ``forward`` returns the PRE-POOL output, ``pool`` halves the resolution."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.norm = nn.BatchNorm2d(in_channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size=1, bias=False)
        self.pool = nn.AvgPool2d(kernel_size=2, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) → (B, out_channels, H/2, W/2)."""
        result: torch.Tensor = self.conv(self.relu(self.norm(x)))
        return result


class DenseNetEncoder(nn.Module):
    """DenseNet-BC encoder with the D3-Net stem for any number of input bands.

    Args:
        in_channels: input bands C.
        growth_rate: k.
        block_config: dense layers per block (4 blocks; DenseNet-121: ``(6, 12, 24, 16)``).
        num_init_features: stem channels.
        bn_size: bottleneck multiplier.
        compression: transition channel compression (0.5 in DenseNet-BC).

    Attributes:
        out_channels: channels of the five returned feature maps (stride 2, 4, 8, 16, 32); for
            DenseNet-121 ``(64, 128, 256, 512, 1024)``.
        reductions: their output strides ``(2, 4, 8, 16, 32)``.
    """

    def __init__(
        self,
        in_channels: int = 3,
        growth_rate: int = 32,
        block_config: Sequence[int] = (6, 12, 24, 16),
        num_init_features: int = 64,
        bn_size: int = 4,
        compression: float = 0.5,
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        f = nn.Module()
        f.conv0 = nn.Conv2d(in_channels, num_init_features, kernel_size=3, stride=2, padding=1, bias=False)
        f.norm0 = nn.BatchNorm2d(num_init_features)
        f.relu0 = nn.LeakyReLU(0.2, inplace=True)
        f.downconv0 = nn.Conv2d(num_init_features, num_init_features, kernel_size=4, stride=2, padding=1, bias=False)
        f.norm1 = nn.BatchNorm2d(num_init_features)
        f.relu1 = nn.LeakyReLU(0.2, inplace=True)
        skips = [num_init_features]
        channels = num_init_features
        n_blocks = len(block_config)
        for i, n_layers in enumerate(block_config):
            block = DenseBlock(n_layers, channels, growth_rate, bn_size)
            f.add_module(f"denseblock{i + 1}", block)
            channels = block.out_channels
            if i != n_blocks - 1:
                out = int(channels * compression)
                f.add_module(f"transition{i + 1}", Transition(channels, out))
                channels = out
                skips.append(channels)
        f.norm5 = nn.BatchNorm2d(channels)
        f.relu5 = nn.LeakyReLU(0.2, inplace=True)
        skips.append(channels)
        self.features = f
        self.n_blocks = n_blocks
        self.out_channels: tuple[int, ...] = tuple(skips)
        self.reductions: tuple[int, ...] = tuple(2 ** (i + 1) for i in range(len(skips)))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He-normal convolutions, BN weight 1 / bias 0 (the torchvision DenseNet initialisation)."""
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Encode an image.

        Args:
            x: B×C×H×W normalised image, H and W multiples of 32.

        Returns:
            Five feature maps, highest resolution first: strides 2, 4, 8, 16, 32 with
            ``self.out_channels`` channels (stem skip, three pre-pool transition outputs, bottleneck).
        """
        f: Any = self.features  # a ModuleDict: its entries are called as modules
        stem = f.relu0(f.norm0(f.conv0(x)))
        out = f.relu1(f.norm1(f.downconv0(stem)))
        feats = [stem]
        for i in range(1, self.n_blocks + 1):
            out = getattr(f, f"denseblock{i}")(out)
            if i != self.n_blocks:
                trans: Transition = getattr(f, f"transition{i}")
                skip = trans(out)
                feats.append(skip)
                out = trans.pool(skip)
        feats.append(f.relu5(f.norm5(out)))
        return feats


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


__all__ = ["DenseLayer", "DenseBlock", "Transition", "DenseNetEncoder", "count_parameters"]
