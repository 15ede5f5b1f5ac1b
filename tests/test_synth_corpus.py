"""A corpus of synthetic towns (aerialmtl.data.synth.corpus): one mosaic per layer, towns kept apart."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import rasterio

from aerialmtl.data.synth.corpus import synthesize_corpus
from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import tile_dataset


def test_every_town_is_in_the_mosaic_and_the_gaps_are_nodata(tmp_path: Path) -> None:
    res = synthesize_corpus(tmp_path / "c", towns=3, size=48, gsd=0.6, seed=5, crs="EPSG:2994", gap_px=16)
    info = json.loads((tmp_path / "c" / "corpus.json").read_text())
    assert [t["seed"] for t in info["town_list"]] == [5, 6, 7]
    assert len({t["sun_azimuth"] for t in info["town_list"]}) == 3  # one sun per town
    with rasterio.open(res.ortho) as m, rasterio.open(res.ndsm) as h:
        assert m.crs.to_epsg() == 2994 and h.crs == m.crs
        assert abs(m.res[0] * 0.3048 - 0.6) < 1e-9  # 0.6 m pixels in a feet CRS
        assert (m.width, m.height) == (2 * 48 + 16, 2 * 48 + 16)  # 2 columns, 2 rows of towns
        img, ndsm, mask = m.read(), h.read(1), m.dataset_mask()
    with rasterio.open(tmp_path / "c" / "town_002" / "ortho.tif") as t2, \
            rasterio.open(tmp_path / "c" / "town_002" / "ndsm.tif") as n2:
        np.testing.assert_array_equal(img[:, 64:112, 0:48], t2.read())  # third town: row 1, column 0
        np.testing.assert_array_equal(ndsm[64:112, 0:48], n2.read(1))
    assert (mask[48:64, :] == 0).all() and (mask[:, 48:64] == 0).all()
    assert (mask[64:, 64:] == 0).all()  # no fourth town
    assert mask[:48, :48].mean() > 0.99


def test_tiles_never_mix_two_towns(tmp_path: Path) -> None:
    res = synthesize_corpus(tmp_path / "c", towns=2, size=64, gsd=0.5, gap_px=32)
    out = tile_dataset(res.ortho, tmp_path / "t", ndsm=res.ndsm, labels=res.labels, classes=res.classes,
                       size=32, stride=16, splits=SplitSpec(block_size=1000.0, ratios=(1, 0, 0)), progress=False)
    assert out.counts["train"] > 0
    with (tmp_path / "t" / "manifest.csv").open() as fh:
        cols = [int(r["col_off"]) for r in csv.DictReader(fh)]
    assert all(c + 32 <= 64 or c >= 96 for c in cols)  # town 0: columns 0-63, town 1: 96-159


def test_refuses_bad_options_and_an_existing_corpus(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="towns"):
        synthesize_corpus(tmp_path / "a", towns=0)
    with pytest.raises(InputError, match="gap_px"):
        synthesize_corpus(tmp_path / "a", towns=1, gap_px=-1)
    synthesize_corpus(tmp_path / "b", towns=1, size=32)
    with pytest.raises(OutputExistsError, match="overwrite"):
        synthesize_corpus(tmp_path / "b", towns=1, size=32)
    res = synthesize_corpus(tmp_path / "b", towns=1, size=32, seed=9, overwrite=True)
    assert json.loads((res.out_dir / "corpus.json").read_text())["town_list"][0]["seed"] == 9
