"""The README's demo, as a user types it, gives the numbers the README states, within their band.

Marked ``demo`` (about 5 minutes on 2 cores): deselected from the README's test command by ``addopts`` and
run by ``.ci/run`` on its own (``python -m pytest -q -m demo``), so a change that moves the demo's model
(a default, a seed, the step budget, the data) fails CI until the expected numbers are measured again.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from helpers.cli import run_cli

from aerialmtl.demo import EXPECTED, EXPECTED_BAND


@pytest.mark.demo
def test_demo_defaults_give_the_stated_numbers(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code, out, err = run_cli(capsys, "demo", tmp_path / "demo_out")
    assert code == 0, err
    got = {}
    for key in EXPECTED:
        m = re.search(rf"^\s*{re.escape(key)}\s+([0-9.]+)\s+expected", out, flags=re.M)
        assert m, f"the demo did not print {key!r} with its expected value:\n{out}"
        got[key] = float(m.group(1))
    outside = {k: v for k, v in got.items() if abs(v - EXPECTED[k]) > EXPECTED_BAND[k]}
    assert not outside, f"outside the stated band: {outside} (expected {EXPECTED} ± {EXPECTED_BAND})"
    assert "outside the expected band" not in out
    assert (tmp_path / "demo_out" / "prediction" / "height.tif").is_file()
