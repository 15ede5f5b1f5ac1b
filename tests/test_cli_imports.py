"""Answers that compute nothing come at once: ``aerialmtl --help``, every ``COMMAND --help``, ``--version`` and
shell completion import neither torch, OpenVINO, numba nor rasterio (GDAL). Each runs in a fresh interpreter (the
console script's own entry point), which then reports the heavy modules it loaded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

#: What a cheap answer must not load (seconds of import time on a cold file cache each).
HEAVY = ("torch", "openvino", "numba", "rasterio", "scipy", "matplotlib")

#: Run the console script's entry point in this interpreter, then print the heavy modules it loaded.
_PROBE = """
import json, sys
sys.argv = ["aerialmtl", *json.loads(sys.argv[1])]
from aerialmtl.__main__ import main
try:
    main()
except SystemExit:
    pass
sys.stdout.flush()
print("\\nLOADED " + json.dumps(sorted(m for m in json.loads(sys.argv_heavy) if m in sys.modules)))
"""


def _loaded(args: list[str], env: dict[str, str] | None = None) -> tuple[list[str], str]:
    """The heavy modules that ``aerialmtl ARGS`` loaded, and what it printed."""
    code = _PROBE.replace("json.loads(sys.argv_heavy)", repr(list(HEAVY)))
    root = Path(__file__).resolve().parents[1]
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]),
                **(env or {})}
    proc = subprocess.run([sys.executable, "-c", code, json.dumps(args)], capture_output=True, text=True,
                          env=full_env, timeout=120, check=False)
    out = proc.stdout
    assert "LOADED " in out, f"aerialmtl {' '.join(args)} failed: {proc.stderr[-2000:]}"
    text, _, loaded = out.rpartition("LOADED ")
    return json.loads(loaded), text


def _commands() -> list[str]:
    from aerialmtl.cli import cli

    return sorted(cli.commands)


def test_commands_listed() -> None:
    assert {"predict", "train", "evaluate", "tile", "bench"} <= set(_commands())


@pytest.mark.parametrize("args", [["--help"], ["--version"], *([c, "--help"] for c in _commands())],
                         ids=lambda a: " ".join(a))
def test_help_imports_nothing_heavy(args: list[str]) -> None:
    loaded, text = _loaded(args)
    assert loaded == [], f"`aerialmtl {' '.join(args)}` imported {loaded}; import them inside the command"
    assert text.strip(), "no answer was printed"


@pytest.mark.parametrize(("words", "cword", "expect"), [
    ("aerialmtl pre", 1, "predict"),
    ("aerialmtl predict --engine ", 3, "openvino"),
    ("aerialmtl predict --precision ", 3, "fp32"),
])
def test_completion_imports_nothing_heavy(words: str, cword: int, expect: str) -> None:
    loaded, text = _loaded([], env={"_AERIALMTL_COMPLETE": "bash_complete", "COMP_WORDS": words,
                                    "COMP_CWORD": str(cword)})
    assert expect in text
    assert loaded == [], f"completion of {words!r} imported {loaded}"


def test_the_predict_modules_load_the_shadow_machinery_only_when_a_run_casts_shadows() -> None:
    """Every predict, evaluate and export reads a checkpoint, whose sun record lives in the sun package: that
    must not import the package's scipy fits and numba kernels (~0.45 s of every start); the package's names
    still resolve, each importing its own module when first asked for."""
    code = ("import json, sys\n"
            "import aerialmtl.formats.checkpoint, aerialmtl.inference.jobs\n"
            "before = sorted(m for m in ('scipy.ndimage', 'scipy.optimize', 'aerialmtl.sun.colour',"
            " 'aerialmtl.sun.kernels', 'aerialmtl.inference.shadows') if m in sys.modules)\n"
            "import aerialmtl.sun as sun\n"
            "names = {n: type(getattr(sun, n)).__name__ for n in sun.__all__}\n"
            "print(json.dumps([before, names, 'aerialmtl.sun.colour' in sys.modules]))\n")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120,
                          check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    before, names, colour_after = json.loads(proc.stdout.strip().splitlines()[-1])
    assert before == [], f"reading a checkpoint / the predict job imported {before}"
    assert set(names) == {"RenderSettings", "RenderedHeights", "ShadowHeights", "ShadowModel", "ShadowObject", "Sun",
                          "SunFit", "cast_shadow_mask", "fit_sun", "fit_sun_patches", "fuse_heights", "fuse_rendered",
                          "rendered_heights", "shadow_heights", "shadow_score"}
    assert colour_after and names["ShadowModel"] == "type" and names["fit_sun"] == "function"
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        import aerialmtl.sun

        _ = aerialmtl.sun.nothing  # type: ignore[attr-defined]
