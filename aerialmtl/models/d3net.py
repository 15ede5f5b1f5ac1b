"""Multi-task D3-Net (Carvalho et al., IEEE GRSL 2019): DenseNet encoder, shared decoder, task decoders.

The encoder is the paper's DenseNet-121 by default; ``cfg.encoder`` may instead choose an
EfficientNet-Lite (:mod:`aerialmtl.models.efficientnet`), whose stride 2/4/8/16/32 stage outputs take the
place of the DenseNet stem, transitions and bottleneck below (same decoder, widths from its channels).

Decoder (facts from the paper and the authors' implementation): five up-blocks bring the stride-32
bottleneck back to full resolution. Up-block ``i`` takes the concatenation ``[encoder skip, previous
output]`` at its input resolution (the deepest block takes the bottleneck alone) and applies

    ConvTranspose2d 4×4 stride 2 pad 1 → BN → [Dropout] → ReLU → Conv 3×3 → BN → [Dropout] → ReLU

(dropout after each BN, in the deepest ``cfg.dropout_blocks`` shared blocks; the authors use two).
The skips concatenated are, from deep to shallow: transition3 (stride 16), transition2 (8),
transition1 (4) and the stem's first activation (2). Each block outputs as many channels as the skip
it is concatenated with next (the last one as many as the stem), which for DenseNet-121 gives the
authors' widths 512, 256, 128, 64, 64. The first ``5 - cfg.task_blocks`` blocks are shared; each task
owns the last ``cfg.task_blocks`` blocks plus a 3×3 output convolution (with bias): ``height`` gives
1 channel in metres (linear), ``classes`` gives K logits. With ``cfg.shadow_head`` a third branch of the same form,
``shadow``, gives one logit of P(cast shadow) (absent otherwise: the paper's network keeps its parameter names).

``encode`` holds the deterministic part (encoder), ``decode`` every dropout layer, so MC dropout
(:mod:`aerialmtl.models.mc_dropout`) runs the encoder once and samples only the decoder.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from typing import TypeVar, cast

import torch
import torch.nn.functional as F
from torch import nn

from aerialmtl.errors import InputError
from aerialmtl.models.config import HEIGHT_BINS, HEIGHT_LAPLACE, HEIGHT_SCALE, SHADOW, ModelConfig
from aerialmtl.models.encoders import encoder_spec, feature_channels
from aerialmtl.models.height_bins import bin_edges, bins_scale

#: H and W of the input must be multiples of this (five stride-2 stages).
SIZE_MULTIPLE = 32

TASK_CHANNELS_HEIGHT = 1
#: Smallest Laplace scale b of an aleatoric height head (metres): keeps the NLL finite on perfect fits.
SCALE_MIN = 0.01
#: Initial raw output of the scale channel: softplus(0.55) + SCALE_MIN ≈ 1 m.
SCALE_INIT = 0.55


def laplace_scale(raw: torch.Tensor) -> torch.Tensor:
    """Raw scale channel → Laplace scale b = softplus(raw) + :data:`SCALE_MIN` (metres, > 0), float32."""
    return F.softplus(raw.float()) + SCALE_MIN


def _activation(name: str) -> nn.Module:
    """``relu`` (the paper's) or ``leaky_relu`` (slope 0.01) as an in-place module."""
    return nn.LeakyReLU(0.01, inplace=True) if name == "leaky_relu" else nn.ReLU(inplace=True)


class UpBlock(nn.Module):
    """ConvTranspose 4×4/2 → BN → [Dropout] → ReLU → conv3×3 → BN → [Dropout] → ReLU.

    Input B×in×h×w → output B×out×2h×2w.
    """

    def __init__(self, in_channels: int, out_channels: int, dropout: float = 0.0, activation: str = "relu") -> None:
        super().__init__()
        # The convolutions feed a BatchNorm, so their bias would be redundant.
        self.up = nn.ConvTranspose2d(in_channels, out_channels, kernel_size=4, stride=2, padding=1, bias=False)
        self.norm1: nn.Module = nn.BatchNorm2d(out_channels)
        self.drop1: nn.Module = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.relu1 = _activation(activation)
        self.conv = nn.Conv2d(out_channels, out_channels, kernel_size=3, padding=1, bias=False)
        self.norm2: nn.Module = nn.BatchNorm2d(out_channels)
        self.drop2: nn.Module = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.relu2 = _activation(activation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, in, h, w) → (B, out, 2h, 2w) (see the class docstring)."""
        x = self.relu1(self.drop1(self.norm1(self.up(x))))
        result: torch.Tensor = self.relu2(self.drop2(self.norm2(self.conv(x))))
        return result


class TaskDecoder(nn.Module):
    """The task-specific up-blocks and the 3×3 output convolution of one task."""

    def __init__(self, blocks: list[UpBlock], in_last: int, out_channels: int) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(blocks)
        self.head = nn.Conv2d(in_last, out_channels, kernel_size=3, padding=1, bias=True)

    def forward(self, x: torch.Tensor, skips: Sequence[torch.Tensor]) -> torch.Tensor:
        """The shared decoder's output ``x`` (B×C×h×w) → the task's raw output (B×out_channels×H×W).

        ``skips`` are the encoder features the task's blocks take, one per block in order (each block
        concatenates its skip with its input, then doubles the resolution).
        """
        for block, skip in zip(self.blocks, skips):
            x = block(torch.cat([skip, x], 1))
        return cast(torch.Tensor, self.head(x))


def pad_to_multiple(x: torch.Tensor, multiple: int = SIZE_MULTIPLE) -> tuple[torch.Tensor, tuple[slice, slice]]:
    """Pad the bottom/right of a B×C×H×W tensor so that H and W are multiples of ``multiple``.

    Reflection padding (replicate where the tensor is too small to reflect).

    Returns:
        ``(padded, crop)``; ``outputs[..., crop[0], crop[1]]`` cuts any model output back to H×W.
    """
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    crop = (slice(0, h), slice(0, w))
    if ph == 0 and pw == 0:
        return x, crop
    mode = "reflect" if (ph < h and pw < w) else "replicate"
    return F.pad(x, (0, pw, 0, ph), mode=mode), crop


class D3Net(nn.Module):
    """Multi-task D3-Net.

    Args:
        cfg: the model configuration (encoder size, tasks, classes, dropout).

    ``forward(x)`` maps a B×C×H×W normalised image (C = ``cfg.in_channels``, H and W multiples of 32)
    to ``{"height": B×1×H×W metres, "classes": B×K×H×W logits}`` for the enabled tasks, plus
    ``"height_scale"`` (B×1×H×W Laplace scale b in metres, > 0) with ``cfg.aleatoric`` (with
    ``cfg.height_bins``: the bins' spread as b = std/√2, and in training mode also ``"height_bins"``, the
    B×K×H×W bin logits, and ``"height_laplace"``, the Laplace scale that trains the height); :attr:`outputs`
    lists the keys of inference in order. With ``cfg.shadow_head`` also ``"shadow"``: B×1×H×W logits of P(cast shadow).
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.tasks: tuple[str, ...] = tuple(cfg.tasks)
        spec = encoder_spec(cfg.encoder)
        self.encoder = spec.build(cfg)
        enc = feature_channels(self.encoder)  # (stem, t1, t2, t3, bottleneck)
        n_up = len(enc)  # 5
        # Block j (0 = deepest) upsamples to the resolution of skip enc[n_up - 2 - j] and outputs its
        # channel count; the last block (to full resolution) keeps the stem width.
        outs = [enc[n_up - 2 - j] for j in range(n_up - 1)] + [enc[0]]
        ins = [enc[-1]] + [outs[j - 1] + enc[n_up - 1 - j] for j in range(1, n_up)]
        n_shared = n_up - cfg.task_blocks
        self.shared = nn.ModuleList(
            UpBlock(ins[j], outs[j], cfg.dropout if j < cfg.dropout_blocks else 0.0) for j in range(n_shared)
        )
        # the height, [a Laplace scale channel unless the scale has its own decoder], [K bin logits]
        scale_channel = int(cfg.aleatoric and not cfg.scale_decoder)
        out_ch = {"height": TASK_CHANNELS_HEIGHT + scale_channel + cfg.height_bins, "classes": cfg.num_classes,
                  SHADOW: 1}

        def task_decoder(channels: int) -> TaskDecoder:
            return TaskDecoder([UpBlock(ins[j], outs[j], activation=cfg.task_activation)
                                for j in range(n_shared, n_up)], outs[-1], channels)

        branches = self.tasks + ((SHADOW,) if cfg.shadow_head else ())
        self.heads = nn.ModuleDict({t: task_decoder(out_ch[t]) for t in branches})
        #: the Laplace scale's own task blocks (``cfg.scale_decoder``); absent otherwise, so the paper's and the
        #: shared-head models keep their parameter names
        self.scale_decoder: TaskDecoder | None = (task_decoder(1) if cfg.scale_decoder and "height" in self.tasks
                                                  else None)
        self.outputs: tuple[str, ...] = cfg.outputs
        self._n_up = n_up
        #: the height bins' edges (metres) with ``cfg.height_bins``; a buffer, so that it follows the device
        self.register_buffer("bin_edges", bin_edges(cfg.height_bins, cfg.height_bin_max) if cfg.height_bins
                             else torch.zeros(0), persistent=False)
        self._reset_decoder()
        if cfg.encoder_weights:
            spec.load_weights(self.encoder, cfg.encoder_weights)

    def _reset_decoder(self) -> None:
        decoders = list(self.heads.values()) + ([self.scale_decoder] if self.scale_decoder is not None else [])
        for m in [m for d in [self.shared, *decoders] for m in d.modules()]:
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        for head in decoders:  # small outputs at start: heights ≈ 0 m, near-uniform softmax
            nn.init.normal_(cast(TaskDecoder, head).head.weight, std=1e-3)
        if self.cfg.aleatoric and "height" in self.heads:  # scale channel: b ≈ 1 m at start (bin logits: 0)
            if self.scale_decoder is not None:
                bias, first = self.scale_decoder.head.bias, 0
            else:
                bias, first = cast(TaskDecoder, self.heads["height"]).head.bias, TASK_CHANNELS_HEIGHT
            assert bias is not None
            nn.init.constant_(bias[first:first + 1], SCALE_INIT)

    def check_input(self, x: torch.Tensor) -> None:
        """Raise :class:`InputError` unless ``x`` is B×C×H×W with C = in_channels and H, W multiples of 32."""
        # a traced graph (the OpenVINO engine) is reshaped to checked windows only
        if torch.jit.is_tracing():  # type: ignore[attr-defined,no-untyped-call]  # not in torch.jit's __all__; unannotated
            return
        c = self.cfg.in_channels
        if x.dim() != 4 or x.shape[1] != c:
            raise InputError(
                f"D3Net input: expected B×{c}×H×W (in_channels={c}), got shape {tuple(x.shape)}; "
                f"pass a batch of {c}-band images or use a model trained on {x.shape[1] if x.dim() == 4 else '?'} bands"
            )
        h, w = x.shape[-2:]
        if h % SIZE_MULTIPLE or w % SIZE_MULTIPLE:
            raise InputError(
                f"D3Net input: H and W must be multiples of {SIZE_MULTIPLE}, got shape {tuple(x.shape)}; "
                f"pad with aerialmtl.models.d3net.pad_to_multiple(x, {SIZE_MULTIPLE}) and crop the outputs, "
                f"or use a tile/patch size that is a multiple of {SIZE_MULTIPLE} (e.g. "
                f"{h + (-h) % SIZE_MULTIPLE}×{w + (-w) % SIZE_MULTIPLE})"
            )

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Deterministic part: B×C×H×W image → encoder features (strides 2, 4, 8, 16, 32)."""
        self.check_input(x)
        result: list[torch.Tensor] = self.encoder(x)
        return result

    def decode(self, feats: list[torch.Tensor], tasks: Collection[str] | None = None) -> dict[str, torch.Tensor]:
        """Stochastic part (every dropout layer): encoder features → ``{output: B×C×H×W}`` (:attr:`outputs`).

        The feature batch may be larger than the image batch (MC samples stacked along B). ``tasks``: decode only
        these tasks' blocks (default all); the dropout layers are all in the shared blocks, so a task's outputs
        do not depend on which others are decoded.
        """
        n = self._n_up
        out = feats[-1]
        for j, block in enumerate(self.shared):
            if j > 0:
                out = torch.cat([feats[n - 1 - j], out], 1)
            out = block(out)
        skips = [feats[n - 1 - j] for j in range(len(self.shared), n)]  # the task blocks' skips, deepest first
        results: dict[str, torch.Tensor] = {}
        for task, dec in self.heads.items():
            if tasks is not None and task not in tasks:
                continue
            y = dec(out, skips)
            if task == "height" and self.cfg.height_bins:
                h = TASK_CHANNELS_HEIGHT
                mu, raw_b, logits = y[:, :h], y[:, h:h + 1], y[:, h + 1:]
                results[task] = mu
                results[HEIGHT_SCALE] = bins_scale(logits, mu.detach(), cast(torch.Tensor, self.bin_edges), SCALE_MIN)
                if self.training:  # the loss needs these; inference (and the engines) only the spread
                    results[HEIGHT_LAPLACE] = laplace_scale(raw_b)
                    results[HEIGHT_BINS] = logits
            elif task == "height" and self.scale_decoder is not None:
                results[task] = y
                results[HEIGHT_SCALE] = laplace_scale(self.scale_decoder(out, skips))
            elif task == "height" and self.cfg.aleatoric:
                results[task] = y[:, :TASK_CHANNELS_HEIGHT]
                results[HEIGHT_SCALE] = laplace_scale(y[:, TASK_CHANNELS_HEIGHT:])
            else:
                results[task] = y
        return results

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """B×C×H×W image → ``{"height": B×1×H×W metres, "classes": B×K×H×W logits}`` (enabled tasks)."""
        return self.decode(self.encode(x))


ModuleT = TypeVar("ModuleT", bound=nn.Module)


def to_channels_last(model: ModuleT) -> ModuleT:
    """``model.to(memory_format=torch.channels_last)``: its 4-D and 5-D parameters and buffers channels-last.

    ``nn.Module.to`` accepts ``memory_format`` but its typed overloads do not list it; the call is typed here once.
    """
    to = cast(Callable[..., ModuleT], model.to)
    return to(memory_format=torch.channels_last)


def encode_features(model: nn.Module, x: torch.Tensor) -> list[torch.Tensor]:
    """``model.encode(x)`` (:meth:`D3Net.encode`) of a D3-Net or a wrapper that forwards it (``torch.compile``'s).

    torch types a module's attributes as ``Tensor | Module``; the call is typed here once.
    """
    return cast(Callable[[torch.Tensor], list[torch.Tensor]], model.encode)(x)


def decode_features(model: nn.Module, feats: list[torch.Tensor],
                    tasks: Collection[str] | None = None) -> dict[str, torch.Tensor]:
    """``model.decode(feats)`` (:meth:`D3Net.decode`) of a D3-Net or a wrapper that forwards it (typed once);
    ``tasks`` (a D3-Net's own decode only): only these tasks' outputs.
    """
    if tasks is None:
        return cast(Callable[[list[torch.Tensor]], dict[str, torch.Tensor]], model.decode)(feats)
    return cast(Callable[..., dict[str, torch.Tensor]], model.decode)(feats, tasks=tasks)


def fold_batchnorm(model: nn.Module) -> nn.Module:
    """A copy of ``model`` for inference with each decoder convolution and its BatchNorm folded into one.

    In every :class:`UpBlock` the (transposed) convolution feeds a BatchNorm directly (dropout comes
    after it), so in eval mode the pair is one affine map: ``BN(conv(x)) = conv'(x)`` with scaled
    weights and a bias (equal up to float rounding, ~1e-7 relative). The encoder (BN → ReLU → conv)
    has nothing to fold. MC dropout is unaffected. The original model is left as it is; a model
    without :class:`UpBlock` is returned itself.
    """
    import copy

    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if not any(isinstance(m, UpBlock) and isinstance(m.norm1, nn.BatchNorm2d) for m in model.modules()):
        return model
    folded = copy.deepcopy(model).eval()
    for m in folded.modules():
        if isinstance(m, UpBlock) and isinstance(m.norm1, nn.BatchNorm2d):
            m.up = fuse_conv_bn_eval(m.up, m.norm1, transpose=True)
            m.norm1 = nn.Identity()
            norm2 = m.norm2
            assert isinstance(norm2, nn.BatchNorm2d), "an UpBlock's two BatchNorms are folded together"
            m.conv = fuse_conv_bn_eval(m.conv, norm2)
            m.norm2 = nn.Identity()
    return folded


def inference_model(model: nn.Module, device: torch.device) -> nn.Module:
    """A copy of ``model`` on ``device`` prepared for prediction: decoder BatchNorms folded
    (:func:`fold_batchnorm`), channels-last activations (measured faster on CPU), eval mode.
    """
    prepared = to_channels_last(fold_batchnorm(model).to(device))
    prepared.eval()
    result: nn.Module = prepared
    return result


__all__ = ["D3Net", "SCALE_MIN", "SIZE_MULTIPLE", "UpBlock", "fold_batchnorm", "inference_model", "laplace_scale",
           "pad_to_multiple"]
