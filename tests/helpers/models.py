"""Tiny models for tests: an identity model whose outputs are its input bands, and a tiny D3-Net."""

from __future__ import annotations

import torch
from torch import nn

from aerialmtl.classes import ClassDef, ClassScheme
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net


class IdentityModel(nn.Module):
    """Receptive-field-free model: height = band 1 de-normalised; class logits = band values (argmax band)."""

    def __init__(self, mean: tuple[float, ...], std: tuple[float, ...], dropout: float = 0.0) -> None:
        super().__init__()
        c = len(mean)
        self.height = nn.Conv2d(c, 1, 1)
        self.classes = nn.Conv2d(c, c, 1)
        self.drop = nn.Dropout2d(dropout)
        with torch.no_grad():
            self.height.weight.zero_()
            self.height.weight[0, 0] = std[0]
            self.height.bias.fill_(mean[0])
            self.classes.weight.copy_(torch.diag(torch.tensor(std, dtype=torch.float32))[:, :, None, None])
            self.classes.bias.copy_(torch.tensor(mean, dtype=torch.float32))

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [x]

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        x = feats[0]
        return {"height": self.height(x), "classes": self.classes(self.drop(x))}

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.decode(self.encode(x))


def identity_meta(bands: int = 3, mean: float = 0.0, std: float = 1.0, gsd: float = 0.5) -> ModelMeta:
    scheme = ClassScheme("bands", tuple(ClassDef(i + 1, f"band {i + 1}", (40 * i, 80, 200 - 40 * i))
                                        for i in range(bands)))
    return ModelMeta(ModelConfig(in_channels=bands, num_classes=bands), scheme, tuple(range(1, bands + 1)),
                     (mean,) * bands, (std,) * bands, gsd)


#: A D3-Net small enough for tests (a few thousand parameters), with dropout.
TINY = dict(growth_rate=4, block_config=(1, 1, 1, 1), num_init_features=8, bn_size=2)


def tiny_d3net(gsd: float = 0.5, k: int = 4, **model: object) -> tuple[D3Net, ModelMeta]:
    """An untrained tiny D3-Net (seed 0) with ``k`` classes of the synthetic scheme, bands r, g, b; ``model``:
    further :class:`ModelConfig` fields (e.g. ``aleatoric=True``)."""
    torch.manual_seed(0)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:k])
    cfg = ModelConfig(num_classes=k, **{**TINY, **model})  # type: ignore[arg-type]
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0, 110.0, 100.0), (40.0, 40.0, 40.0), gsd, ("r", "g", "b"))
    return D3Net(cfg).eval(), meta
