"""The training sun (the shadow classifier's weights included) is the same to the bit whatever thread count the
numerical libraries get: train's sun process (:mod:`aerialmtl.training.sun_beside`) runs with its own thread
limits, and a user re-running a training on another machine or with ``OMP_NUM_THREADS`` set gets the same record."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from aerialmtl.cpuinfo import usable_cpus
from aerialmtl.data.synth import synthesize
from aerialmtl.tiling.tile import TileOptions, tile_dataset

FIT = ("import json, sys; from aerialmtl.config import to_dict; from aerialmtl.training.sun import fit_training_sun; "
       "print(json.dumps(to_dict(fit_training_sun(sys.argv[1])), allow_nan=True))")


@pytest.mark.skipif(usable_cpus() < 2, reason="one core: every BLAS runs one thread, so the counts cannot differ")
def test_the_training_sun_does_not_depend_on_the_blas_thread_count(tmp_path: Path) -> None:
    res = synthesize(tmp_path / "town", size=256, seed=11, gsd=0.5)
    tiles = tmp_path / "tiles"
    tile_dataset(res.ortho, tiles, ndsm=res.ndsm, options=TileOptions(size=64, stride=64), progress=False)
    answers = []
    for threads in ("1", "2"):
        env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
        env["OPENBLAS_NUM_THREADS"] = threads
        done = subprocess.run([sys.executable, "-c", FIT, str(tiles)], env=env, capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        answers.append(done.stdout.strip().splitlines()[-1])
    assert '"shadow_model": {' in answers[0]  # a clear sun with a classifier: the weights are compared
    assert answers[0] == answers[1]
