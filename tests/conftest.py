"""Shared test fixtures: tiny georeferenced rasters generated in ``tmp_path`` with a fixed seed."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator

# Before torch loads OpenMP: threads that sleep instead of spinning while they wait. On a CPU shared with
# other jobs, spinning threads steal the cores the work needs (bench/RESULTS.md, train: 6× slower model
# steps at load 6); results do not change, only their speed. Child processes (torchrun, notebooks) inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import rasterio  # noqa: E402
import torch  # noqa: E402
from affine import Affine  # noqa: E402
from torch import nn  # noqa: E402

from aerialmtl.classes import ClassDef, ClassScheme  # noqa: E402
from aerialmtl.formats.checkpoint import ModelMeta  # noqa: E402
from aerialmtl.models.config import ModelConfig  # noqa: E402
from aerialmtl.models.d3net import D3Net  # noqa: E402

#: Real sample data shipped beside the repository (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NEON_DIR = SHARED_DATA / "neon_bart"

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))

#: ``pytest --cpu-kind K``: the CPU capability probe answers as on that kind of CPU (the bf16 choices of
#: ``precision: auto`` follow), in this process and in the subprocesses tests start.
CPU_KINDS = {"amx": "amx_bf16,avx512_bf16", "avx512bf16": "avx512_bf16", "none": ""}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-kind", choices=sorted(CPU_KINDS), default=None,
                     help="run as on a CPU with AMX-BF16 (amx), AVX-512-BF16 only (avx512bf16) or neither (none); "
                          "default: this machine's CPU")


def pytest_configure(config: pytest.Config) -> None:
    from aerialmtl import runtime

    kind = config.getoption("--cpu-kind")
    if kind is not None:
        os.environ[runtime.CPU_FLAGS_ENV] = CPU_KINDS[kind]
    runtime.cpu_bf16_flags.cache_clear()


def pytest_report_header(config: pytest.Config) -> str:
    from aerialmtl import runtime

    return f"aerialmtl CPU probe: native bf16 flags {runtime.cpu_bf16_flags() or 'none'}"


@pytest.fixture(autouse=True, scope="session")
def _openvino_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The OpenVINO engine's converted models go to a temporary folder, not the user's cache (subprocesses
    inherit it)."""
    os.environ["AERIALMTL_OPENVINO_CACHE"] = str(tmp_path_factory.mktemp("openvino-cache"))


def write_raster(
    path: Path,
    data: np.ndarray,
    crs: str = "EPSG:32631",
    transform: Affine | None = None,
    nodata: float | None = None,
    **extra: object,
) -> Path:
    """Write ``data`` (bands, H, W) or (H, W) as a GeoTIFF; default grid: 0.5 m pixels at (500000, 5000000)."""
    if data.ndim == 2:
        data = data[None]
    transform = transform or Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)
    profile = dict(driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
                   dtype=data.dtype, crs=crs, transform=transform, nodata=nodata, **extra)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def write_prediction_layers(
    folder: Path,
    classes: np.ndarray,
    height: np.ndarray,
    height_std: np.ndarray | None = None,
    entropy: np.ndarray | None = None,
    crs: str = "EPSG:32631",
    transform: Affine | None = None,
    scheme: str | None = "synthetic",
) -> Path:
    """A prediction folder (aerialmtl.formats.prediction) from (H, W) arrays: ``classes.tif`` (uint8, nodata 255,
    tagged with the built-in class ``scheme`` unless ``None``), ``height.tif`` and optional ``height_std.tif`` /
    ``class_entropy.tif`` (float32, nodata -9999); default grid as :func:`write_raster`."""
    import json

    from aerialmtl.classes import ClassScheme
    from aerialmtl.formats.prediction import (
        CLASS_ENTROPY,
        CLASS_NODATA,
        CLASS_SCHEME_TAG,
        CLASSES,
        FLOAT_NODATA,
        HEIGHT,
        HEIGHT_STD,
        layer_filename,
    )

    folder.mkdir(parents=True, exist_ok=True)
    path = write_raster(folder / layer_filename(CLASSES), classes.astype(np.uint8), crs, transform, CLASS_NODATA)
    if scheme is not None:
        with rasterio.open(path, "r+") as dst:
            dst.update_tags(**{CLASS_SCHEME_TAG: json.dumps(ClassScheme.load(scheme).to_dict())})
    for name, data in ((HEIGHT, height), (HEIGHT_STD, height_std), (CLASS_ENTROPY, entropy)):
        if data is not None:
            write_raster(folder / layer_filename(name), data.astype(np.float32), crs, transform, FLOAT_NODATA)
    return folder


def write_prediction_folder(folder: Path, rng: np.random.Generator, size: int = 64) -> Path:
    """A tiny prediction folder with every uncertainty layer on 0.5 m pixels (random values, nodata in the
    upper-left 4×4 corner), plus ``ortho.tif`` beside it at twice the resolution over the same footprint."""
    from aerialmtl.formats.prediction import CLASS_MUTUAL_INFO, CLASS_NODATA, FLOAT_NODATA, layer_filename

    scheme = ClassScheme.load("synthetic")
    height = rng.uniform(0, 20, (size, size)).astype(np.float32)
    std, entropy, mutual_info = (rng.uniform(0, hi, (size, size)).astype(np.float32) for hi in (2.0, 1.0, 1.0))
    cls = rng.integers(0, scheme.num_classes, (size, size)).astype(np.uint8)
    for layer in (height, std, entropy, mutual_info):
        layer[:4, :4] = FLOAT_NODATA
    cls[:4, :4] = CLASS_NODATA
    write_prediction_layers(folder, cls, height, std, entropy)
    write_raster(folder / layer_filename(CLASS_MUTUAL_INFO), mutual_info, nodata=FLOAT_NODATA)
    write_raster(folder.parent / "ortho.tif", rng.integers(0, 255, (3, 2 * size, 2 * size)).astype(np.uint8),
                 transform=Affine(0.25, 0, 500000.0, 0, -0.25, 5000000.0))
    return folder


def run_cli(capsys: pytest.CaptureFixture, *args: object) -> tuple[int, str, str]:
    """Run ``aerialmtl ARGS`` in-process like the console script; returns (exit code, stdout, stderr)."""
    from aerialmtl.cli import main

    capsys.readouterr()
    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


# ---- tiny models ------------------------------------------------------------------------------
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


def tiny_d3net(gsd: float = 0.5, k: int = 4) -> tuple[D3Net, ModelMeta]:
    """An untrained tiny D3-Net (seed 0) with ``k`` classes of the synthetic scheme, bands r, g, b."""
    torch.manual_seed(0)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:k])
    cfg = ModelConfig(num_classes=k, **TINY)  # type: ignore[arg-type]
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0, 110.0, 100.0), (40.0, 40.0, 40.0), gsd, ("r", "g", "b"))
    return D3Net(cfg).eval(), meta


def mount_tmpfs(folder: Path, options: str) -> Iterator[Path]:
    """Mount a tmpfs with ``options`` at ``folder`` for a fixture (root on Linux only; skipped where mounting
    is not permitted), unmounted after it."""
    folder.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True,
                              text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"cannot mount a tmpfs here ({exc})")
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root: {done.stderr.strip()[:100]})")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True, timeout=30)
