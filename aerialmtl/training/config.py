"""Training configuration: YAML → frozen dataclasses (validated by :func:`aerialmtl.config.from_dict`).

A config file has the sections below; every key is optional and defaults to the D3-Net paper's
setting. Unknown keys, wrong types and bad choices raise :class:`~aerialmtl.errors.ConfigError` naming
the key path (``optim.lr``) and the valid keys/choices::

    model:     {block_config: [6, 12, 24, 16], dropout: 0.5, ..., sync_bn: false}   # ModelConfig; in_channels,
                                                                   # num_classes, tasks from dataset.yaml
    data:      {dir: tiles/, batch_size: 8, num_workers: 2, flips: true, rot90: true, jitter: false,
                crop_size: null, cache_dir: null, copy_paste: {prob: 0.0, max_objects: 3, min_height_m: 2.5}}
    loss:      {height: l1, classes: ce, class_weights: none}      # or balanced, or a list of K floats
    weighting: {method: equal, task_weights: {height: 1.0, classes: 1.0}}
    optim:     {name: adam, lr: 2.0e-4, betas: [0.5, 0.999], weight_decay: 0.0, ema: null}
    schedule:  {epochs: 50, max_steps: null, max_time_s: null, val_every: 1, log_every: 10, patience: null,
                lr_schedule: constant, warmup_steps: 0}
    seed: 0
    device: auto          # auto | cpu | cuda
    precision: auto       # auto (bf16 autocast on a CUDA GPU that has bf16, fp32 otherwise) | fp32 | bf16
    compile: false        # torch.compile the model (falls back to eager with a warning if it fails)
    calibration: {enabled: true, method: isotonic, mc_samples: 16}   # fitted on val after training
    familiarity: {enabled: true, levels: [2], dims: 32, method: gda}  # feature density fitted on train
    sun: {enabled: true}          # the training area's sun and shadow classifier, fitted on train (predict --sun)

Relative ``data.dir`` paths are resolved against the current working directory. With several processes
(``torchrun``), ``data.batch_size`` is per process: a step uses ``batch_size × processes`` patches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Literal

from aerialmtl.config import from_dict, load_yaml_config, to_dict
from aerialmtl.data.copy_paste import CopyPaste
from aerialmtl.errors import ConfigError
from aerialmtl.models.config import Architecture, ModelConfig, Task, check_data_fields

HeightLoss = Literal["l1", "l2", "huber", "berhu", "scale_invariant", "scale_invariant_gradient"]


@dataclass(frozen=True)
class ModelSection(Architecture):
    """The ``model`` section: the architecture, and the model fields the tile folder gives by default.

    An :class:`~aerialmtl.models.config.Architecture` plus the data-dependent fields of
    :class:`~aerialmtl.models.config.ModelConfig`, which default to ``None`` = taken from the tile folder.

    ``in_channels`` comes from the number of bands, ``num_classes`` from the class scheme and ``tasks``
    from the tasks present in ``dataset.yaml``; a value given here must agree with the data.

    ``sync_bn`` is a training option, not part of the model (it is not saved in :class:`ModelConfig`):
    with several processes, BatchNorm statistics are computed over the global batch instead of each
    process's share. It has no effect in a single process.
    """

    in_channels: int | None = None
    tasks: tuple[Task, ...] | None = None
    num_classes: int | None = None
    sync_bn: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        check_data_fields(self.in_channels, None if self.tasks is None else tuple(self.tasks), self.num_classes)

    def resolve(self, in_channels: int, tasks: tuple[str, ...], num_classes: int | None) -> ModelConfig:
        """The :class:`ModelConfig` for a tile folder with these bands, tasks and classes.

        Raises:
            ConfigError: an explicit value disagrees with the data (names the key and both values).
        """
        if self.in_channels is not None and self.in_channels != in_channels:
            raise ConfigError(
                f"model.in_channels: the config says {self.in_channels} but the tile folder has {in_channels} "
                "bands; remove model.in_channels or tile with matching --bands"
            )
        want = tuple(self.tasks) if self.tasks is not None else tuple(tasks)
        missing = [t for t in want if t not in tasks]
        if missing:
            raise ConfigError(
                f"model.tasks: {missing} requested but the tile folder only has {list(tasks) or 'no references'}; "
                "remove them from model.tasks or tile with that reference layer"
            )
        if "classes" in want:
            if num_classes is None:
                raise ConfigError("model.tasks: 'classes' needs a class scheme in dataset.yaml")
            if self.num_classes is not None and self.num_classes != num_classes:
                raise ConfigError(
                    f"model.num_classes: the config says {self.num_classes} but the tile folder's class scheme "
                    f"has {num_classes}; remove model.num_classes or use the matching scheme"
                )
            k = num_classes
        else:
            k = self.num_classes if self.num_classes is not None else ModelConfig.num_classes
        values = {f.name: getattr(self, f.name) for f in fields(Architecture)}
        values.update(in_channels=in_channels, tasks=want, num_classes=k)
        return ModelConfig(**values)


@dataclass(frozen=True)
class DataSection:
    """Where the tiles are and how they are batched and augmented.

    Attributes:
        dir: tile folder written by ``aerialmtl tile`` (``--data`` overrides it).
        batch_size: patches per optimisation step and process (with ``torchrun --nproc_per_node N``
            a step uses ``N × batch_size`` patches).
        num_workers: DataLoader worker processes of a GPU run (0 = load in the main process), and the processes
            that decode the patch cache on first use. A CPU run takes its batches from one thread of the training
            process instead (:mod:`aerialmtl.data.prefetch`: cheaper than worker processes on the cores the step
            uses).
        flips, rot90: random horizontal/vertical flips and 90° rotations.
        jitter: photometric jitter (contrast/brightness in normalised space).
        crop_size: random crop side in pixels (multiple of 32), ``None`` = whole patches.
        cache_dir: folder of the decoded patch cache, ``None`` = ``cache/`` inside the tile folder, or
            ``$XDG_CACHE_HOME/aerialmtl/<hash>`` (with a warning) when that cannot be written (written on
            first use; see :mod:`aerialmtl.data.cache`).
        copy_paste: paste the train split's tall objects (image, heights and labels together) into other
            training patches (:class:`~aerialmtl.data.copy_paste.CopyPaste`; off unless ``prob > 0``).
    """

    dir: str | None = None
    batch_size: int = 8
    num_workers: int = 2
    flips: bool = True
    rot90: bool = True
    jitter: bool = False
    crop_size: int | None = None
    cache_dir: str | None = None
    copy_paste: CopyPaste = field(default_factory=CopyPaste)

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ConfigError(f"data.batch_size: must be ≥ 1, got {self.batch_size}")
        if self.num_workers < 0:
            raise ConfigError(f"data.num_workers: must be ≥ 0, got {self.num_workers}")
        if self.crop_size is not None and (self.crop_size < 32 or self.crop_size % 32):
            raise ConfigError(f"data.crop_size: must be a multiple of 32 (the network's stride), got {self.crop_size}")


@dataclass(frozen=True)
class LossSection:
    """Per-task losses: ``height`` (masked to valid pixels) and ``classes`` (cross-entropy, ignore 255).

    With ``model.aleatoric: true`` the height loss is the Laplace negative log-likelihood
    (:func:`~aerialmtl.training.losses.laplace_nll`), the likelihood of the paper's L1; ``height`` must then
    be ``l1``, and ``nll_beta`` (β-NLL, 0 … 1) sets how much the learned scale down-weights hard pixels'
    pull on the heights (0: plain NLL; 1: the heights get L1's gradient). With ``model.height_bins`` the
    height loss adds ``bins_weight`` × the cross-entropy of the reference height's bin
    (:mod:`aerialmtl.models.height_bins`).

    ``height_balance`` (0 … 1; 0, the paper: every pixel alike) weighs each pixel's height loss by
    ``n_k^−height_balance``, ``n_k`` the batch's pixels in its reference-height bin (0–1, 1–2, 2–5, 5–10, 10–20,
    ≥ 20 m), normalised to mean 1 (:func:`~aerialmtl.training.losses.height_balance_weights`): an option against
    tall structures outvoted by ground. Validation still scores the plain L1.

    ``class_weights``: ``none``, ``balanced`` (``N / (K · n_k)`` from the train split's pixel counts,
    normalised to mean 1 over present classes) or an explicit list of K floats.

    ``shadow_weight`` (with ``model.shadow_head``): the weight of the shadow head's binary cross-entropy (nats) in
    the training loss, beside the task weighting (:mod:`aerialmtl.training.objective`).
    """

    height: HeightLoss = "l1"
    classes: Literal["ce"] = "ce"
    class_weights: Literal["none", "balanced"] | tuple[float, ...] = "none"
    nll_beta: float = 0.0
    bins_weight: float = 1.0
    height_balance: float = 0.0
    shadow_weight: float = 1.0

    def __post_init__(self) -> None:
        if not (isinstance(self.shadow_weight, (int, float)) and 0.0 <= float(self.shadow_weight) <= 100.0):
            raise ConfigError(f"loss.shadow_weight: must be a number in [0, 100], got {self.shadow_weight!r}; 1 "
                              "weighs the shadow head's cross-entropy (nats) like the L1 height loss (metres)")
        if not (isinstance(self.height_balance, (int, float)) and 0.0 <= float(self.height_balance) <= 1.0):
            raise ConfigError(f"loss.height_balance: must be a number in [0, 1], got {self.height_balance!r}; 0 "
                              "weighs every pixel alike (the paper), 0.5 by the inverse square root of its height "
                              "bin's share of the batch")
        if self.height_balance and self.height != "l1":
            raise ConfigError(f"loss.height_balance: weighs the L1 / Laplace height loss; loss.height is "
                              f"{self.height!r}: set loss.height: l1 or loss.height_balance: 0")
        if not (isinstance(self.bins_weight, (int, float)) and 0.0 < float(self.bins_weight) <= 100.0):
            raise ConfigError(f"loss.bins_weight: must be a number in (0, 100], got {self.bins_weight!r}; 1 weighs "
                              "the height bins' cross-entropy (nats) like the L1 height loss (metres)")
        if not (isinstance(self.nll_beta, (int, float)) and 0.0 <= float(self.nll_beta) <= 1.0):
            raise ConfigError(f"loss.nll_beta: must be a number in [0, 1], got {self.nll_beta!r}; 0 is the plain "
                              "Laplace NLL of Kendall & Gal, 1 trains the heights exactly as L1 does")
        if isinstance(self.class_weights, tuple):
            bad = [w for w in self.class_weights if not (math.isfinite(w) and w >= 0)]
            if bad or not any(w > 0 for w in self.class_weights):
                raise ConfigError(
                    f"loss.class_weights: must be finite weights ≥ 0 with at least one > 0, got "
                    f"{list(self.class_weights)}; or use 'none' or 'balanced'"
                )


@dataclass(frozen=True)
class WeightingSection:
    """How task losses are combined: ``equal`` (sum) or ``uncertainty`` (learned, Kendall et al.).

    ``task_weights`` multiply each task loss before the weighting module (default 1 each).
    """

    method: Literal["equal", "uncertainty"] = "equal"
    task_weights: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bad = [k for k in self.task_weights if k not in ("height", "classes")]
        if bad:
            raise ConfigError(f"weighting.task_weights: unknown task {bad[0]!r}; valid tasks are height, classes")
        for task, w in self.task_weights.items():
            if not (math.isfinite(w) and w >= 0):
                raise ConfigError(f"weighting.task_weights.{task}: must be a finite weight ≥ 0, got {w}")


@dataclass(frozen=True)
class OptimSection:
    """Optimiser (the paper: Adam, lr 2e-4, β = (0.5, 0.999)).

    ``weight_decay`` applies to the network's convolution weights only, never to biases, BatchNorm
    parameters or the learned task weighting: L2 in the gradient with ``adam``, decoupled with ``adamw``.

    ``ema`` (``None``: off, the paper's setting) is the decay of an exponential moving average of the weights
    and BatchNorm statistics, updated after every step (:mod:`aerialmtl.training.averaging`): validation,
    ``best.pt`` and ``last.pt`` use the average (``last.pt`` also keeps the raw weights to resume). 0.99
    averages over about the last 100 steps, which makes a short training's outcome far less sensitive to
    float rounding (bench/RESULTS.md, "the demo across CPU kinds").
    """

    name: Literal["adam", "adamw"] = "adam"
    lr: float = 2e-4
    betas: tuple[float, float] = (0.5, 0.999)
    weight_decay: float = 0.0
    ema: float | None = None

    def __post_init__(self) -> None:
        # written as `not (in range)` so that NaN (given from Python, YAML's .nan is refused earlier) fails too
        if not 0.0 < self.lr <= 1.0:
            raise ConfigError(f"optim.lr: must be a learning rate in (0, 1], got {self.lr}; the paper uses 2.0e-4")
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise ConfigError(f"optim.betas: must be two decay rates in [0, 1), got {list(self.betas)}; "
                              "the paper uses [0.5, 0.999]")
        if not 0.0 <= self.weight_decay < 1.0:
            raise ConfigError(f"optim.weight_decay: must be ≥ 0 and < 1, got {self.weight_decay}; e.g. 1.0e-4, or 0")
        if self.ema is not None and not 0.0 < self.ema < 1.0:
            raise ConfigError(f"optim.ema: must be a decay in (0, 1), got {self.ema}; e.g. 0.99 (about the last "
                              "100 steps), or null for no average")


@dataclass(frozen=True)
class ScheduleSection:
    """When to stop, validate and log.

    Attributes:
        epochs: passes over the train split.
        max_steps: stop after this many optimisation steps (``None`` = no limit).
        max_time_s: wall-clock budget in seconds; training stops cleanly and saves when it is spent.
        val_every: validate every this many epochs (and always at the end).
        log_every: write a training row to ``log.csv`` every this many steps.
        patience: early stopping: stop after this many validations in a row without a better score
            (``best.pt`` keeps the best model); ``None`` = never.
        lr_schedule: ``constant`` (the paper's ``optim.lr`` throughout) or ``cosine`` (from ``optim.lr`` down
            to 0 over the run's planned steps: this section's ``max_steps`` when set, else ``epochs`` × steps per
            epoch; a run stopped earlier — ``--max-steps``, ``max_time_s``, ``patience`` — ends before the
            learning rate reaches 0, and resumed, it continues the same schedule).
        warmup_steps: the learning rate grows linearly from ``optim.lr / warmup_steps`` to ``optim.lr`` over
            the first this many steps (0: no warm-up), then follows ``lr_schedule``.
    """

    epochs: int = 50
    max_steps: int | None = None
    max_time_s: float | None = None
    val_every: int = 1
    log_every: int = 10
    patience: int | None = None
    lr_schedule: Literal["constant", "cosine"] = "constant"
    warmup_steps: int = 0

    def __post_init__(self) -> None:
        if self.warmup_steps < 0:
            raise ConfigError(f"schedule.warmup_steps: must be ≥ 0, got {self.warmup_steps}")
        for name in ("epochs", "val_every", "log_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"schedule.{name}: must be ≥ 1, got {getattr(self, name)}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ConfigError(f"schedule.max_steps: must be ≥ 1, got {self.max_steps}")
        if self.max_time_s is not None and not self.max_time_s > 0:
            raise ConfigError(f"schedule.max_time_s: must be > 0, got {self.max_time_s}")
        if self.patience is not None and self.patience < 1:
            raise ConfigError(f"schedule.patience: must be ≥ 1 validations, got {self.patience}")


@dataclass(frozen=True)
class CalibrationSection:
    """Calibration fitted on the validation split at the end of training (:mod:`aerialmtl.training.calibrate`).

    Attributes:
        enabled: fit a height map and a spread factor on the val patches and store them in ``best.pt``
            and ``last.pt`` (``predict`` applies them unless ``--no-calibration``).
        method: ``isotonic`` (validation mean of the reference among pixels predicted alike) or
            ``median`` (the same with medians: an L1 fit) or ``quantile`` (predicted height quantiles mapped to
            reference quantiles).
        mc_samples: MC-dropout samples per validation patch.
    """

    enabled: bool = True
    method: Literal["isotonic", "median", "quantile"] = "isotonic"
    mc_samples: int = 16

    def __post_init__(self) -> None:
        if self.mc_samples < 1:
            raise ConfigError(f"calibration.mc_samples: must be ≥ 1, got {self.mc_samples}")


@dataclass(frozen=True)
class FamiliaritySection:
    """The ``familiarity`` section: the encoder-feature density fitted on the train split at the end of training.

    Fitted by :mod:`aerialmtl.training.familiarity`; ``predict`` writes the ``unfamiliarity`` layer from it.

    Attributes:
        enabled: fit it and store it in ``best.pt`` and ``last.pt``.
        levels: encoder outputs used (0..4 = strides 2, 4, 8, 16, 32); the default, stride 8, was chosen on
            validation among strides 4-32, level pairs, EM mixtures, densities given the prediction and nearest
            neighbours (bench/RESULTS.md, "unfamiliarity").
        dims: principal axes kept.
        method: ``gda`` (one Gaussian per reference-height bin, DDU's choice) or ``em`` (a mixture fitted by EM).
        components: Gaussians of ``em``.
    """

    enabled: bool = True
    levels: tuple[int, ...] = (2,)
    dims: int = 32
    method: Literal["gda", "em"] = "gda"
    components: int = 8

    def __post_init__(self) -> None:
        if not self.levels or any(not 0 <= v <= 4 for v in self.levels):
            raise ConfigError(f"familiarity.levels: encoder levels 0..4 (strides 2..32), got {list(self.levels)}")
        if self.dims < 1 or self.components < 1:
            raise ConfigError(f"familiarity.dims and familiarity.components: must be ≥ 1, got {self.dims} and "
                              f"{self.components}")


@dataclass(frozen=True)
class SunSection:
    """The ``sun`` section: the training area's sun and shadow classifier, fitted at the end of training.

    Fitted on the train split by :mod:`aerialmtl.training.sun`; ``predict --sun`` writes the ``shadow`` and
    ``shadow_height`` layers from them.

    Attributes:
        enabled: fit them and store them in ``best.pt`` and ``last.pt`` (a tile folder without heights or
            8-bit RGB patches fits nothing, with one line saying so).
    """

    enabled: bool = True


@dataclass(frozen=True)
class TrainConfig:
    """The whole training configuration (see the module docstring for the YAML layout)."""

    model: ModelSection = field(default_factory=ModelSection)
    data: DataSection = field(default_factory=DataSection)
    loss: LossSection = field(default_factory=LossSection)
    weighting: WeightingSection = field(default_factory=WeightingSection)
    optim: OptimSection = field(default_factory=OptimSection)
    schedule: ScheduleSection = field(default_factory=ScheduleSection)
    seed: int = 0
    device: Literal["auto", "cpu", "cuda"] = "auto"
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    compile: bool = False
    calibration: CalibrationSection = field(default_factory=CalibrationSection)
    familiarity: FamiliaritySection = field(default_factory=FamiliaritySection)
    sun: SunSection = field(default_factory=SunSection)
    #: Keys of earlier configs (and of the configs stored in earlier checkpoints) read and ignored, with a warning:
    #: ``predict`` held ``mc_samples``, which nothing read; ``predict --mc`` and
    #: :class:`~aerialmtl.inference.settings.PredictSettings` decide T (30 with dropout).
    REMOVED_KEYS: ClassVar[dict[str, str]] = {
        "predict": "predict's MC samples are predict's own option (--mc; 30 by default with dropout)"}

    def __post_init__(self) -> None:
        if not 0 <= self.seed < 2**63:
            raise ConfigError(f"seed: must be an integer in 0..2**63-1, got {self.seed}")
        if self.model.aleatoric and self.loss.height != "l1":
            raise ConfigError(f"loss.height: with model.aleatoric the height loss is the Laplace NLL, the likelihood "
                              f"of L1; set loss.height: l1 (got {self.loss.height!r}) or model.aleatoric: false")

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping (YAML / checkpoint safe)."""
        result: dict[str, Any] = to_dict(self)
        return result

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> TrainConfig:
        """A config from a plain dict (a YAML's), validated."""
        return from_dict(cls, data)

    def with_overrides(self, **sections: Any) -> TrainConfig:
        """A copy with some keys replaced, e.g. ``cfg.with_overrides(schedule={"max_steps": 10}, seed=1)``.

        Values are validated like YAML values.
        """
        data = self.to_dict()
        for key, value in sections.items():
            if isinstance(value, dict) and isinstance(data.get(key), dict):
                data[key] = {**data[key], **value}
            else:
                data[key] = value
        return from_dict(TrainConfig, data)


def load_train_config(path: str | Path) -> TrainConfig:
    """Read a training YAML file (errors name the file and the key path)."""
    return load_yaml_config(path, TrainConfig)


__all__ = ["TrainConfig", "ModelSection", "DataSection", "LossSection", "WeightingSection", "OptimSection",
           "ScheduleSection", "load_train_config"]
