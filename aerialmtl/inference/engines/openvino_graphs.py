"""The OpenVINO engine's graphs: the modules traced for conversion, their outputs' layout, the cache.

The modules: forward, encoder, and decoder with explicit dropout masks. The cache: its location and key.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import nn

from aerialmtl.inference.model_record import CheckpointModel
from aerialmtl.models.d3net import decode_features, encode_features
from aerialmtl.models.mc_dropout import _SEEDABLE
from aerialmtl.stores import open_store_folder

#: Side of the example input the model is converted with (any multiple of 32; small converts fast).
CONVERT_SIZE = 64
#: Outputs of the forward graph (T = 1) that leave it channels last, ``(1, h, w, C)``, instead of ``(1, C, h, w)``:
#: the host's softmax wants the classes of a pixel side by side, and OpenVINO's convolutions store them so (class
#: planes cost a reorder there and a transposing copy on the host: 0.84× the CPU of predict at T = 1, 8192², on
#: the near-null D3-Net of ``bench/predict.py`` with trained-like head biases; bench/RESULTS.md, issue 27). The
#: decoder graph (T > 1) does the same: the CPU's MC class kernel (:mod:`aerialmtl.models.class_kernel`) turns a
#: row into class planes in the cache, where OpenVINO's reorder to planes cost up to 75 ms per 1024² sample. The
#: engine hands them on as views in the models' ``(B, C, h, w)`` order (:func:`_as_planes`).
FORWARD_CHANNELS_LAST = ("classes",)
#: Version of the converted graphs' outputs (part of the cache key: a cache of other outputs is never read).
GRAPH_OUTPUTS = "forward-decoder-classes-nhwc"



def cache_root() -> Path | None:
    """Root of the OpenVINO caches: the ``openvino`` store, or ``None`` where no folder can hold it.

    The store's folder is :func:`aerialmtl.stores.store_folder`'s; ``None`` comes with one warning.
    """
    return open_store_folder("openvino", "the converted OpenVINO model")


def fingerprint(model: nn.Module, extra: str = "") -> str:
    """A hash of the weights and buffers of ``model``, its class and ``extra`` (configuration, versions)."""
    h = hashlib.blake2b(digest_size=12)
    h.update(f"{type(model).__module__}.{type(model).__qualname__}|{extra}".encode())
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        if t.numel():
            h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()


class _MaskMul(nn.Module):
    """A dropout layer whose mask is an input: ``x · mask`` (mask set by :class:`_Decoder` per call)."""

    def __init__(self) -> None:
        super().__init__()
        self.mask: torch.Tensor | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        assert self.mask is not None
        return x * self.mask


def model_outputs(model: nn.Module | CheckpointModel, tasks: Sequence[str]) -> tuple[str, ...]:
    """The keys of ``model``'s output dict in order: its ``outputs``, else ``tasks``.

    A D3-Net's ``outputs`` are the tasks, plus ``height_scale`` for an aleatoric head.
    """
    return tuple(getattr(model, "outputs", None) or tasks)


def _graph_output(task: str, t: torch.Tensor) -> torch.Tensor:
    """Output ``task`` of a traced graph (forward or decoder), in the layout the graph returns.

    ``(1, C, h, w)`` → ``(1, h, w, C)`` for :data:`FORWARD_CHANNELS_LAST`.
    """
    return t.permute(0, 2, 3, 1) if task in FORWARD_CHANNELS_LAST else t


def _as_planes(task: str, t: torch.Tensor) -> torch.Tensor:
    """A graph's output ``task`` in the models' ``(B, C, h, w)`` order.

    For :data:`FORWARD_CHANNELS_LAST`, a view of a channels-last ``(B, h, w, C)`` array (no copy: the softmax and
    the MC class kernel read it channels last).
    """
    return t.permute(0, 3, 1, 2) if task in FORWARD_CHANNELS_LAST else t


class _Forward(nn.Module):
    def __init__(self, model: nn.Module, tasks: Sequence[str]) -> None:
        super().__init__()
        self.model, self.tasks = model, model_outputs(model, tasks)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(x)
        return tuple(_graph_output(t, out[t]) for t in self.tasks)


class _Encoder(nn.Module):
    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(encode_features(self.model, x))


class _Decoder(nn.Module):
    """``decode`` with the seedable dropout layers replaced by :class:`_MaskMul` (masks as inputs)."""

    def __init__(self, model: nn.Module, tasks: Sequence[str], n_feats: int) -> None:
        super().__init__()
        import copy

        self.model = copy.deepcopy(model).eval()
        self.tasks, self.n_feats = model_outputs(model, tasks), n_feats
        self.sites: list[_MaskMul] = []
        for parent in list(self.model.modules()):
            for name, child in list(parent.named_children()):
                if isinstance(child, _SEEDABLE) and float(child.p) > 0:
                    mul = _MaskMul()
                    setattr(parent, name, mul)
                    self.sites.append(mul)

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        feats, masks = list(inputs[:self.n_feats]), inputs[self.n_feats:]
        for site, mask in zip(self.sites, masks):
            site.mask = mask
        out = decode_features(self.model, feats)
        return tuple(_graph_output(t, out[t]) for t in self.tasks)



__all__ = ["CONVERT_SIZE", "FORWARD_CHANNELS_LAST", "GRAPH_OUTPUTS", "cache_root", "fingerprint", "model_outputs"]
