"""How well the training flight's chips (aerialmtl.sun.flight) tell the same flight from another, on real
orthophotos: the same pixels regridded, recompressed or coarsened must match (r ≥ SAME_FLIGHT_R); the same
orthophoto registered 1 m off (as another flight's orthorectification is) must not.

    PYTHONPATH=. python experiments/heights_from_the_sun/flight_chips.py [--out flight_chips.md]

Each orthophoto of ../shared/data gives N_CHIPS chips (64 px, textured, seeded), kept as `train` keeps them; each
variant is written as a GeoTIFF and matched by ``predict``'s own reader (aerialmtl.inference.sun_choice.flight_match).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.warp import Resampling, reproject

from aerialmtl.inference.sun_choice import flight_match
from aerialmtl.sun.flight import CHIP_PX, N_CHIPS, SAME_FLIGHT_R, FlightChip, cut_chip
from aerialmtl.sun.record import TrainingSun

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
ORTHOS = ["autzen_west/ortho_1ft.tif", "flair_annecy/ortho_0p2m_l93.tif",
          "ign_montpellier_lidarhd/ortho_0p2m_l93.tif", "neon_bart/rgb_0p1m.tif"]


def chips_of(src: rasterio.DatasetReader, seed: int = 0) -> tuple[FlightChip, ...]:
    """N_CHIPS textured chips at seeded places of ``src`` (as train cuts them from its patches)."""
    rng = np.random.default_rng(seed)
    chips: list[FlightChip] = []
    for _ in range(2000):
        r, c = int(rng.integers(0, src.height - CHIP_PX)), int(rng.integers(0, src.width - CHIP_PX))
        window = ((r, r + CHIP_PX), (c, c + CHIP_PX))
        t = src.window_transform(window)
        chip = cut_chip(src.read([1, 2, 3], window=window), np.ones((CHIP_PX, CHIP_PX), bool), t.c, t.f, t.a)
        if chip is not None:
            chips.append(chip)
        if len(chips) == N_CHIPS:
            break
    return tuple(chips)


def variant(src: rasterio.DatasetReader, out: Path, shift_px: float = 0.0, scale: int = 1, jpeg: int | None = None,
            label_shift_px: float = 0.0) -> Path:
    """``src`` resampled (bilinear) onto its grid moved by ``shift_px`` pixels and ``scale`` times coarser, written
    with its georeference moved by ``label_shift_px`` pixels more (a misregistration), JPEG at quality ``jpeg``."""
    grid = src.transform * Affine.translation(shift_px, shift_px) * Affine.scale(scale)
    h, w = src.height // scale - 1, src.width // scale - 1
    data = np.zeros((3, h, w), np.uint8)
    for b in range(3):
        reproject(rasterio.band(src, b + 1), data[b], dst_transform=grid, dst_crs=src.crs,
                  resampling=Resampling.average if scale > 1 else Resampling.bilinear)
    extra = dict(compress="JPEG", jpeg_quality=jpeg, tiled=True) if jpeg else {}
    written = grid * Affine.translation(label_shift_px / scale, label_shift_px / scale)
    with rasterio.open(out, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=src.crs,
                       transform=written, **extra) as dst:
        dst.write(data)
    return out


def _chips_at_1m(name: str, tmp: Path) -> str:
    """One table row: chips of ``name`` averaged to 1 m, matched against ``name`` itself and registered 1 m off."""
    with rasterio.open(DATA / name) as src:
        px_m = src.res[0] * src.crs.linear_units_factor[1]
        scale = int(round(1.0 / px_m))
        coarse = variant(src, tmp / "at1m.tif", scale=scale)
        off = variant(src, tmp / "off1m.tif", label_shift_px=1.0 / px_m)
        crs = src.crs.to_string()
    with rasterio.open(coarse) as at1m:
        if min(at1m.width, at1m.height) < 2 * CHIP_PX:
            return f"| {name.split('/')[0]} | too small at 1 m | – |"
        fit = TrainingSun(clear=False, reason="chips only", crs=crs, chips=chips_of(at1m))
    cells = [flight_match(p, fit) for p in (DATA / name, off)]
    return f"| {name.split('/')[0]} | " + " | ".join("–" if m.r is None else f"{m.r:.3f} ({m.chips})"
                                                    for m in cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="also write the table to this Markdown file")
    args = ap.parse_args()
    lines = ["| orthophoto | pixel (m) | itself | 0.4 px regrid + JPEG 60 | 2× coarser | 3× coarser | 1 m off "
             "| 2× coarser, 1 m off |",
             "|---|---|---|---|---|---|---|---|"]
    tiles: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in ORTHOS:
            with rasterio.open(DATA / name) as src:
                unit = src.crs.linear_units_factor[1]
                px_m = src.res[0] * unit
                fit = TrainingSun(clear=False, reason="chips only", crs=src.crs.to_string(), chips=chips_of(src))
                cases = {"itself": DATA / name,
                         "regrid": variant(src, Path(tmp) / "regrid.tif", shift_px=0.4, jpeg=60),
                         "2x": variant(src, Path(tmp) / "x2.tif", scale=2),
                         "3x": variant(src, Path(tmp) / "x3.tif", scale=3),
                         "1 m off": variant(src, Path(tmp) / "off.tif", label_shift_px=1.0 / px_m),
                         "2x, 1 m off": variant(src, Path(tmp) / "x2off.tif", scale=2, label_shift_px=1.0 / px_m)}
                cells = []
                for path in cases.values():
                    m = flight_match(path, fit)
                    cells.append("–" if m.r is None else f"{m.r:.3f} ({m.chips})")
            lines.append(f"| {name.split('/')[0]} | {px_m:.2f} | " + " | ".join(cells) + " |")
            tiles.append(_chips_at_1m(name, Path(tmp)))
    lines.append(f"\nMedian r over the chips compared (in brackets); another flight below {SAME_FLIGHT_R}.\n")
    lines += ["Chips cut from the orthophoto averaged to 1 m (as `tile --gsd 1` makes the patches), matched against",
              "the orthophoto at its own pixel:\n", "| orthophoto | itself | 1 m off |", "|---|---|---|", *tiles]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
