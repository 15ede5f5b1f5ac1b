"""Planning a prediction job: shares of the bands over processes, and VRT mosaics over different grids."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers.rasters import write_raster

from aerialmtl.errors import InputError
from aerialmtl.inference.jobs import Share, partition, targets_for
from aerialmtl.io.vrt import mosaic_vrt


def test_partition_gives_contiguous_equal_shares_and_keeps_small_inputs_whole() -> None:
    assert partition([[1.0] * 2] * 3, 1) == [[Share(0, 0, 2), Share(1, 0, 2), Share(2, 0, 2)]]
    shares = partition([[1.0] * 2] * 3, 2)  # 6 bands over 2 ranks: the middle input is cut
    assert shares == [[Share(0, 0, 2), Share(1, 0, 1)], [Share(1, 1, 2), Share(2, 0, 2)]]
    shares = partition([[1.0] * 8], 3)  # one raster, three strips of about equal size
    assert [(s.start, s.stop) for r in shares for s in r] == [(0, 3), (3, 5), (5, 8)]
    covered = sorted((s.target, b) for r in partition([[1, 2, 3], [5], [1] * 4], 4) for s in r
                     for b in range(s.start, s.stop))
    assert covered == [(0, 0), (0, 1), (0, 2), (1, 0), (2, 0), (2, 1), (2, 2), (2, 3)]  # each band once
    assert sum(len(r) for r in partition([[1.0]], 3)) == 1  # more ranks than bands: some get nothing


def test_targets_one_folder_per_stem_and_clashes_refused(tmp_path: Path) -> None:
    assert [t.out for t in targets_for(["a/x.tif"], tmp_path)] == [tmp_path]
    assert [t.out for t in targets_for(["a/x.tif", "b/y.tif"], tmp_path)] == [tmp_path / "x", tmp_path / "y"]
    with pytest.raises(InputError, match="share the file stem"):
        targets_for(["a/x.tif", "b/x.tif"], tmp_path)


def test_mosaic_over_other_resolutions_and_crs(tmp_path: Path) -> None:
    def layer(name: str, value: float, transform: Affine, crs: str = "EPSG:32631") -> Path:
        data = np.full((1, 40, 40), value, np.float32)
        data[0, :4, :4] = -9999.0  # nodata: transparent in the mosaic
        return write_raster(tmp_path / name, data, crs, transform, nodata=-9999.0)

    a = layer("a.tif", 1.0, Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0))
    b = layer("b.tif", 2.0, Affine(1.0, 0, 500030.0, 0, -1.0, 4999990.0))  # coarser
    # the same place in the next UTM zone (500010, 4999990 in zone 31N)
    c = layer("c.tif", 3.0, Affine(0.5, 0, 28386.28, 0, -0.5, 5017529.5), crs="EPSG:32632")
    out = mosaic_vrt(tmp_path / "m.vrt", [a, b, c])
    with rasterio.open(out) as vrt, rasterio.open(c) as cc:
        assert vrt.crs == "EPSG:32631" and vrt.res == (0.5, 0.5) and vrt.nodata == -9999.0
        for path in (a, b):
            with rasterio.open(path) as src:
                win = vrt.window(*src.bounds)
                vals = vrt.read(1, window=win)
                assert set(np.unique(vals)) <= {-9999.0, 1.0, 2.0, 3.0} and (vals != -9999.0).any()
        assert 3.0 in np.unique(vrt.read(1))  # the other-CRS input is reprojected into the mosaic
        assert cc.crs == "EPSG:32632"
        assert vrt.read(1)[0, 0] == -9999.0 and vrt.read(1)[5, 5] == 1.0
    assert (tmp_path / "m.warped").is_dir()
    with pytest.raises(InputError, match="band"):
        mosaic_vrt(tmp_path / "bad.vrt", [a, write_raster(tmp_path / "u8.tif", np.zeros((1, 8, 8), np.uint8))])
