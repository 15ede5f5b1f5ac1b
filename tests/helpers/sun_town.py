"""A synthetic town under a known sun and a tiny D3-Net whose checkpoint holds that sun's fit (its shadow
classifier included): what `predict --sun-tune` needs, for the tests that run it in one process and under torchrun.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from affine import Affine

from aerialmtl.data.synth import CityStyle, sample_city
from aerialmtl.formats.checkpoint import ModelMeta, save_checkpoint
from aerialmtl.sun import ShadowModel, Sun
from aerialmtl.sun.record import TrainingSun

from .models import tiny_d3net
from .rasters import write_raster

SUN = Sun(135.0, 45.0)
ORIGIN = (500000.0, 5000064.0)  # EPSG:32631 on the central meridian: grid north = true north
SIZE = 128


def normalised_image(image: np.ndarray, meta: ModelMeta) -> torch.Tensor:
    """(1, C, H, W) float32 of a (C, H, W) image as the model takes it (``(x − mean) / std``)."""
    img = torch.from_numpy(np.asarray(image, np.float32))
    return ((img - torch.tensor(meta.mean)[:, None, None]) / torch.tensor(meta.std)[:, None, None])[None]


def fit_heights(model: torch.nn.Module, meta: ModelMeta, image: np.ndarray, height: np.ndarray,
                steps: int = 40) -> None:
    """A few L1 steps on the town itself (seed 0): with 40, a network whose heights have objects, read low (its
    tallest ~9 m where the town's is 14 m), as a network trained elsewhere reads a new area."""
    torch.manual_seed(0)
    x, y = normalised_image(image, meta), torch.from_numpy(np.asarray(height, np.float32))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    model.train()
    for _ in range(steps):
        opt.zero_grad()
        (model(x)["height"][0, 0] - y).abs().mean().backward()
        opt.step()
    model.eval()


def sun_town(root: Path) -> dict[str, object]:
    """A 128 px town at 0.5 m under :data:`SUN` written to ``root/town.tif``, and ``root/m.pt``: a tiny D3-Net fitted
    40 steps on it (:func:`fit_heights`) whose training fit is that sun. Keys: root, ckpt, ortho, image, height."""
    style = dataclasses.replace(CityStyle.plain().with_lean(0.0), sun_azimuth=(SUN.azimuth_deg,) * 2,
                                sun_elevation=(SUN.elevation_deg,) * 2)
    patch = sample_city(3, size=SIZE, gsd=0.5, style=style)
    write_raster(root / "town.tif", patch.image, transform=Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1]))
    shadows = ShadowModel().fit(patch.image, patch.height, 0.5, SUN)
    fit = TrainingSun(clear=True, reason="sun fitted (the town)", azimuth_deg=SUN.azimuth_deg,
                      elevation_deg=SUN.elevation_deg, grid_azimuth_deg=SUN.azimuth_deg, score=0.5, sharpness=0.5,
                      crs="EPSG:32631", bounds=(ORIGIN[0], ORIGIN[1] - SIZE * 0.5, ORIGIN[0] + SIZE * 0.5, ORIGIN[1]),
                      shadow_model=shadows.to_dict())
    model, meta = tiny_d3net()
    fit_heights(model, meta, patch.image, patch.height)
    save_checkpoint(root / "m.pt", model, dataclasses.replace(meta, sun=fit))
    return {"root": root, "ckpt": root / "m.pt", "ortho": root / "town.tif", "image": patch.image,
            "height": patch.height}
