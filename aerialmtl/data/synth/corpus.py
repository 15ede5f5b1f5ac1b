"""Many synthetic towns as one dataset: the corpus a model is pretrained on before a small real area.

:func:`synthesize_corpus` writes ``towns`` towns (seeds ``seed``, ``seed + 1``, ...; each its own sun
angle, layout rotation and materials) with :func:`~aerialmtl.data.synth.synthesize`, laid out on a grid
in one CRS with ``gap_px`` empty pixels between neighbours, and one mosaic VRT per layer
(:func:`aerialmtl.io.vrt.mosaic_vrt`), so that ``tile_dataset(ortho.vrt, ndsm=ndsm.vrt,
labels=labels.vrt, classes=classes.yaml)`` cuts them all in one pass. The gaps read as nodata; with a
gap at least as wide as the patches, no patch ever mixes two towns (patches over the gaps fail the
tiler's valid-fraction test)::

    OUT/town_000/{ortho,dsm,dtm,ndsm,labels}.tif, OUT/town_001/..., ...
    OUT/{ortho,dsm,dtm,ndsm,labels}.vrt, OUT/classes.yaml, OUT/corpus.json (seeds, sun angles, layout)

The orthophoto mosaic declares nodata 0 (synthetic images have no nodata of their own), so a pixel
whose three bands are all exactly 0 inside a town also counts as invalid; the renderer's ambient light
keeps such pixels out in practice.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rasterio.crs import CRS

from aerialmtl.data.synth.generate import MIN_SIZE, SYNTH_VERSION, synthesize
from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.io.align import HEIGHT_NODATA
from aerialmtl.io.vrt import mosaic_vrt

#: Layers mosaicked, with the nodata of pixels outside every town.
MOSAIC_LAYERS = {"ortho": 0, "dsm": HEIGHT_NODATA, "dtm": HEIGHT_NODATA, "ndsm": HEIGHT_NODATA, "labels": 0}


@dataclass(frozen=True)
class CorpusResult:
    """Paths of the corpus written by :func:`synthesize_corpus` (VRT mosaics and the class scheme)."""

    out_dir: Path
    ortho: Path
    dsm: Path
    dtm: Path
    ndsm: Path
    labels: Path
    classes: Path
    towns: int
    seconds: float


def synthesize_corpus(
    out_dir: str | Path,
    towns: int = 16,
    size: int = 1024,
    gsd: float = 0.25,
    seed: int = 0,
    crs: str = "EPSG:32631",
    gap_px: int = 512,
    overwrite: bool = False,
    on_town: Callable[[int, int], None] | None = None,
) -> CorpusResult:
    """Write ``towns`` synthetic towns of ``size`` px at ``gsd`` metres and mosaic VRTs over them.

    Args:
        out_dir: output folder.
        towns: number of towns (seeds ``seed`` … ``seed + towns - 1``).
        size: side of each town in pixels (≥ the synthesiser's minimum).
        gsd: pixel size in metres (use the working GSD of the real area).
        seed: seed of the first town.
        crs: projected CRS of the corpus (metres or feet; the GSD stays in metres).
        gap_px: empty pixels between neighbouring towns; at least the patch size you tile with.
        overwrite: replace an existing corpus in ``out_dir``.
        on_town: called as ``on_town(done, towns)`` after each town (progress reporting).

    Returns:
        A :class:`CorpusResult`.

    Raises:
        InputError: ``towns`` < 1, ``gap_px`` < 0, or what :func:`synthesize` refuses (size, gsd, crs).
        OutputExistsError: ``out_dir`` holds a corpus and ``overwrite`` is False.
    """
    t0 = time.perf_counter()
    if int(towns) != towns or towns < 1:
        raise InputError(f"‹towns› must be a positive number of towns, got {towns}; pass e.g. ‹towns=16›",
                         param="towns")
    if int(gap_px) != gap_px or gap_px < 0:
        raise InputError(f"‹gap_px› must be a number of pixels ≥ 0, got {gap_px}; use at least the patch size",
                         param="gap_px")
    if int(size) != size or size < MIN_SIZE:
        raise InputError(f"‹size› must be an integer ≥ {MIN_SIZE} pixels, got {size}; pass e.g. ‹size=1024›",
                         param="size")
    out = Path(out_dir)
    info_path = out / "corpus.json"
    if info_path.exists() or any((out / f"{name}.vrt").exists() for name in MOSAIC_LAYERS):
        if not overwrite:
            raise OutputExistsError(f"'{out}' already holds a synthetic corpus; pass ‹overwrite=True› to replace it "
                                    "or choose another ‹out_dir›")
        for child in out.glob("town_*"):
            shutil.rmtree(child)
    out.mkdir(parents=True, exist_ok=True)
    crs_obj = CRS.from_user_input(crs)
    unit = float(crs_obj.linear_units_factor[1]) if crs_obj.is_projected else 1.0
    step = (size + gap_px) * gsd / unit  # CRS units between neighbouring towns' origins
    ncols = math.ceil(math.sqrt(towns))
    records = []
    for i in range(towns):
        row, col = divmod(i, ncols)
        origin = (500000.0 + col * step, 5000000.0 - row * step)
        res = synthesize(out / f"town_{i:03d}", size=size, seed=seed + i, gsd=gsd, crs=crs, origin=origin,
                         overwrite=overwrite)
        records.append({"seed": seed + i, "row": row, "col": col, "sun_azimuth": res.sun_azimuth,
                        "sun_elevation": res.sun_elevation})
        if on_town is not None:
            on_town(i + 1, towns)
    paths = {}
    for name, nodata in MOSAIC_LAYERS.items():
        paths[name] = mosaic_vrt([out / f"town_{i:03d}" / f"{name}.tif" for i in range(towns)],
                                 out / f"{name}.vrt", nodata=nodata)
    classes = out / "classes.yaml"
    shutil.copyfile(out / "town_000" / "classes.yaml", classes)
    info = {"synth_version": SYNTH_VERSION, "towns": towns, "size": size, "gsd": gsd, "seed": seed,
            "crs": crs_obj.to_string(), "gap_px": gap_px, "layout_columns": ncols, "town_list": records,
            "files": [f"{n}.vrt" for n in MOSAIC_LAYERS] + ["classes.yaml"]}
    info_path.write_text(json.dumps(info, indent=1))
    return CorpusResult(out, paths["ortho"], paths["dsm"], paths["dtm"], paths["ndsm"], paths["labels"], classes,
                        towns, time.perf_counter() - t0)


__all__ = ["CorpusResult", "MOSAIC_LAYERS", "synthesize_corpus"]
