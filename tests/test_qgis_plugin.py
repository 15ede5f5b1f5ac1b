"""The QGIS Processing plugin: parameters → command lines, progress, Cancel (without QGIS), and a headless QGIS run.

The plugin's QGIS-free modules (:mod:`aerialmtl.qgis_plugin.spec`, :mod:`aerialmtl.qgis_plugin.runner`) are
tested here against the real command line. ``test_headless_qgis`` runs the plugin, installed from its zip,
inside QGIS (``python3-qgis``: QGIS's own Python, not this one) and skips where QGIS is not installed.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path
from typing import Any

import click
import numpy as np
import pytest
import rasterio
import torch
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_raster

from aerialmtl import __version__
from aerialmtl.cli import cli
from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.formats.prediction import LAYERS, layer_filename
from aerialmtl.plugin_zip import PLUGIN_FILES, PLUGIN_FOLDER, PLUGIN_SOURCE
from aerialmtl.qgis_plugin.runner import Progress, parse_progress, run_command
from aerialmtl.qgis_plugin.spec import (
    ALGORITHMS,
    PREDICT,
    PREDICTION_LAYERS,
    command_line,
    dialog_message,
    not_found_message,
)

REPO = Path(__file__).resolve().parents[1]
#: The command line of this checkout, as the plugin would run the installed `aerialmtl` program.
PROGRAM = [sys.executable, "-m", "aerialmtl"]
#: QGIS's Python (Debian's python3-qgis lives in the system Python); AERIALMTL_QGIS_PYTHON to choose another.
QGIS_PYTHON = os.environ.get("AERIALMTL_QGIS_PYTHON", "/usr/bin/python3")


# ---- parameters → command lines ---------------------------------------------------------------------
def test_predict_command_line() -> None:
    argv = command_line("/opt/bin/aerialmtl", PREDICT, {
        "INPUT": "/data/ortho.tif", "MODEL": "/runs/a/best.pt", "MC": 8, "AOI": "", "ENGINE": "openvino",
        "PRECISION": "auto", "DEVICE": "cpu", "WINDOW": 512, "OVERLAP": 64.0, "PROBABILITIES": False,
        "NO_CALIBRATION": True, "RESCALE_INPUT": False, "OVERWRITE": True, "OUTPUT": "/maps/a"})
    assert argv == ["/opt/bin/aerialmtl", "--progress", "json", "predict",
                    "--model", "/runs/a/best.pt", "--mc", "8", "--engine", "openvino", "--precision", "auto",
                    "--device", "cpu", "--window", "512", "--overlap", "64", "--no-calibration", "--overwrite",
                    "--out", "/maps/a", "--", "/data/ortho.tif"]
    # left empty: the command's own default (the model from AERIALMTL_MODEL, T from the model)
    assert command_line("aerialmtl", PREDICT, {"INPUT": "o.tif", "OUTPUT": "p"}) == [
        "aerialmtl", "--progress", "json", "predict", "--out", "p", "--", "o.tif"]
    assert command_line(["python", "-m", "aerialmtl"], ALGORITHMS["buildings"], {
        "INPUT": "p", "MIN_AREA": 2.5, "OUTPUT": "b.gpkg"}) == [
        "python", "-m", "aerialmtl", "--progress", "json", "buildings", "--min-area", "2.5", "--out", "b.gpkg", "--",
        "p"]


@pytest.mark.parametrize("name", ["-x.tif", "--help", "-h"])
def test_positional_paths_that_look_like_options_stay_paths(name: str, tmp_path: Path) -> None:
    """A file the user named ``-x.tif`` or ``--help`` reaches the command as a path (after ``--``), not as an
    option: the command says the file is missing, it does not print its help or "No such option"."""
    from helpers.procs import aerialmtl, env

    argv = command_line(["x"], PREDICT, {"INPUT": name, "MODEL": str(tmp_path / "m.pt"), "OUTPUT": "p"})
    done = aerialmtl(*argv[1:], environ=env(), cwd=tmp_path, timeout=300)
    text = " ".join((done.stdout + done.stderr).split())
    assert done.returncode == 2, text  # a bad value of the ORTHOS argument: click's usage error
    assert f"'{name}' does not exist" in text and "No such option" not in text and "Options:" not in text


def test_command_line_refuses_missing_and_unknown_values() -> None:
    with pytest.raises(ValueError, match="'Orthophoto' needs a value"):
        command_line("aerialmtl", PREDICT, {"OUTPUT": "p"})
    with pytest.raises(ValueError, match="must be one of auto, bf16, fp32, got 'fp16'"):
        command_line("aerialmtl", PREDICT, {"INPUT": "o.tif", "OUTPUT": "p", "PRECISION": "fp16"})


def test_errors_name_the_dialogs_fields_not_the_flags() -> None:
    """Raised from QGIS, the command's message names the dialog's fields (and the parameter names scripts pass)."""
    text = "prediction folder 'p' already holds height.tif; pass --overwrite to replace them or choose another --out"
    assert dialog_message(PREDICT, text) == (
        "prediction folder 'p' already holds height.tif; tick 'Replace existing outputs' (OVERWRITE) to replace them "
        "or choose another 'Prediction folder' (OUTPUT)")
    assert dialog_message(PREDICT, "--overlap 2000 is larger than --window 1024") == (
        "'Minimum overlap between windows (pixels)' (OVERLAP) 2000 is larger than "
        "'Largest window side (pixels, multiple of 32)' (WINDOW) 1024")
    assert dialog_message(PREDICT, "--model RUN/best.pt") == "'Model checkpoint (best.pt)' (MODEL) RUN/best.pt"
    assert dialog_message(PREDICT, "no flag here --outer") == "no flag here --outer"
    assert dialog_message(ALGORITHMS["export"], "Invalid value for 'CHECKPOINT': File 'm.pt' does not exist.") == (
        f"Invalid value for '{ALGORITHMS['export'].params[0].label}' (INPUT): File 'm.pt' does not exist.")


#: Options the toolbox does not offer: the terminal's --quiet, what Processing's batch mode replaces (several
#: inputs, --skip-existing), tuning knobs with sound defaults; a new option of a command fails the test below
#: until it is offered or listed here.
LEFT_OUT = {
    # --tile: --window's old name; --threads: predict runs with auto, like --batch-size
    "predict": {"--quiet", "--skip-existing", "--batch-size", "--compile", "--tile", "--threads", "--max-decode-pixels",
                "--reader-threads"},
    "buildings": {"--quiet", "--block-size", "--simplify"},
    "evaluate": {"--quiet", "--sample-size", "--seed", "--height-bins", "--height-threshold", "--ignore-unknown-codes",
                 "--pred-buildings"},
    "tile": {"--quiet", "--min-valid", "--split-block", "--split-ratios", "--split-seed", "--split-aoi",
             "--clip-negative", "--max-height", "--ignore-unknown-codes"},
    "train": {"--quiet", "--compile"},
    "export": {"--overlap"},
}


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_every_parameter_is_an_option_of_the_command(name: str) -> None:
    """The plugin's flags, kinds, choices and defaults are those of the command line it runs, and it offers
    every option of the command but those in LEFT_OUT."""
    algorithm = ALGORITHMS[name]
    command = cli.commands[name]
    options = {o: p for p in command.params for o in p.opts}
    arguments = [p for p in command.params if isinstance(p, click.Argument)]
    assert [p.flag for p in algorithm.params if p.flag is None] == [None] * len(arguments)
    for p in algorithm.params:
        if p.flag is None:
            continue
        assert p.flag in options, f"{name}: {p.flag} is not an option of `aerialmtl {name}`"
        option = options[p.flag]
        assert isinstance(option, click.Option)
        assert (p.kind == "bool") == option.is_flag, p.flag
        if p.kind == "enum":
            assert isinstance(option.type, click.Choice) and p.choices == tuple(option.type.choices), p.flag
        if p.kind == "int":
            assert isinstance(option.type, (click.types.IntParamType, click.IntRange)), p.flag
        if p.kind == "float":
            assert isinstance(option.type, (click.types.FloatParamType, click.FloatRange)), p.flag
        if p.default is not None and p.kind != "bool":
            assert option.default == p.default, f"{name} {p.flag}: default {p.default} != {option.default}"
        if option.required:
            assert not p.optional, p.flag
    options_of_command = {o.opts[0] for o in command.params if isinstance(o, click.Option) and o.name != "help"}
    assert LEFT_OUT[name] <= options_of_command, name  # the list below stays current
    missing = options_of_command - {p.flag for p in algorithm.params} - LEFT_OUT[name]
    assert not missing, f"{name}: the plugin does not offer {sorted(missing)}"
    required = {o.opts[0] for o in command.params if isinstance(o, click.Option) and o.required}
    assert required <= {p.flag for p in algorithm.params if not p.optional}


def test_prediction_layers_are_the_prediction_files() -> None:
    assert [f for f, _ in PREDICTION_LAYERS] == [layer_filename(n) for n in LAYERS]


# ---- progress lines ---------------------------------------------------------------------------------
def test_parse_progress() -> None:
    assert parse_progress('{"stage": "o.tif", "done": 3, "total": 12, "unit": "win"}\n') == Progress(
        "o.tif", 3, 12, "win")
    assert parse_progress('{"stage": "o.tif", "done": 3, "total": 12}').percent == 25.0  # type: ignore[union-attr]
    assert parse_progress('{"stage": "evaluate", "done": 3, "total": null}').percent is None  # type: ignore[union-attr]
    for line in ("warning: {x}", "Error: bad", "{not json", '{"stage": "x"}', '{"done": "many"}', ""):
        assert parse_progress(line) is None


# ---- running the real command line ----------------------------------------------------------------
@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny model that sees buildings (class 'building' favoured), a small and a larger orthophoto."""
    folder = tmp_path_factory.mktemp("qgis-inputs")
    model, meta = tiny_d3net()
    with torch.no_grad():
        model.heads.classes.head.bias[2] += 3.0  # index 2 = 'building' of the synthetic scheme
    save_checkpoint(folder / "m.pt", model, meta)
    rng = np.random.default_rng(0)
    small = write_raster(folder / "ortho.tif", rng.integers(0, 255, (3, 128, 128)).astype(np.uint8))
    big = write_raster(folder / "big.tif", rng.integers(0, 255, (3, 640, 640)).astype(np.uint8))
    write_raster(folder / "ndsm.tif", rng.uniform(0, 10, (128, 128)).astype(np.float32))  # a reference for evaluate
    return {"model": folder / "m.pt", "ortho": small, "big": big}


def _env() -> dict[str, str]:
    """This checkout first on the path of the commands the tests start."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def test_run_reports_progress_to_100_percent(inputs: dict[str, Path], tmp_path: Path) -> None:
    seen: list[Progress] = []
    messages: list[tuple[str, str]] = []
    argv = command_line(PROGRAM, PREDICT, {"INPUT": str(inputs["ortho"]), "MODEL": str(inputs["model"]), "MC": 3,
                                           "WINDOW": 64, "OVERLAP": 16, "OUTPUT": str(tmp_path / "p")})
    result = run_command(argv, seen.append, lambda kind, text: messages.append((kind, text)), env=_env())
    assert result.ok, result.message()
    assert seen[0].done == 0 and seen[-1].percent == 100.0 and seen[-1].stage == "ortho.tif"
    assert any(kind == "info" and "ortho.tif → " in text for kind, text in messages)  # the result line
    assert (tmp_path / "p" / "height_std.tif").is_file()


def test_cancel_stops_the_command_and_leaves_nothing(inputs: dict[str, Path], tmp_path: Path) -> None:
    seen: list[Progress] = []
    argv = command_line(PROGRAM, PREDICT, {"INPUT": str(inputs["big"]), "MODEL": str(inputs["model"]), "MC": 8,
                                           "WINDOW": 64, "OVERLAP": 16, "OUTPUT": str(tmp_path / "p")})
    result = run_command(argv, seen.append, is_canceled=lambda: any(p.done > 0 for p in seen), env=_env())
    assert result.canceled and result.returncode == 143  # SIGTERM, handled like Ctrl-C
    assert 0 < seen[-1].done < seen[-1].total  # type: ignore[operator]  # stopped mid-run
    assert result.message().startswith("canceled: interrupted; no output was left at a final path")
    assert not (tmp_path / "p").exists() or not any((tmp_path / "p").iterdir())


def test_errors_are_the_one_line_message(inputs: dict[str, Path], tmp_path: Path) -> None:
    argv = command_line(PROGRAM, PREDICT, {"INPUT": str(inputs["ortho"]), "MODEL": str(tmp_path / "none.pt"),
                                           "OUTPUT": str(tmp_path / "p")})
    result = run_command(argv, env=_env())
    assert result.returncode == 1 and not result.ok
    assert "none.pt" in result.message() and "\n" not in result.message() and "Traceback" not in result.message()


def test_a_command_that_ignores_sigterm_is_killed(tmp_path: Path) -> None:
    script = tmp_path / "stubborn.py"
    script.write_text(textwrap.dedent("""
        import signal, sys, time
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        print('{"stage": "x", "done": 1, "total": 9}', file=sys.stderr, flush=True)
        time.sleep(60)
    """))
    seen: list[Progress] = []
    start = time.monotonic()
    result = run_command([sys.executable, str(script)], seen.append, is_canceled=lambda: bool(seen), grace_s=1.0)
    assert result.canceled and result.returncode == -9 and time.monotonic() - start < 30


def test_a_missing_program_says_where_to_set_it(tmp_path: Path) -> None:
    with pytest.raises(OSError) as info:
        run_command([str(tmp_path / "aerialmtl")])
    message = not_found_message(str(tmp_path / "aerialmtl"), info.value)
    assert str(tmp_path / "aerialmtl") in message and "Providers → aerialmtl" in message


# ---- the zip ----------------------------------------------------------------------------------------
def test_plugin_zip(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code, out, err = run_cli(capsys, "qgis-plugin", tmp_path / "dist" / "plugin.zip")
    assert code == 0, err
    assert "Install from ZIP" in out
    with zipfile.ZipFile(tmp_path / "dist" / "plugin.zip") as zf:
        assert sorted(zf.namelist()) == sorted(f"{PLUGIN_FOLDER}/{f}" for f in PLUGIN_FILES)
        metadata = zf.read(f"{PLUGIN_FOLDER}/metadata.txt").decode()
    assert "qgisMinimumVersion=3.22" in metadata and f"version={__version__}\n" in metadata
    # every source file of the plugin is packed (a new module would otherwise be missing in QGIS)
    assert {p.name for p in PLUGIN_SOURCE.iterdir() if p.suffix in (".py", ".txt")} == set(PLUGIN_FILES)
    code, _, err = run_cli(capsys, "qgis-plugin", tmp_path / "dist" / "plugin.zip")
    assert code == 1 and "--overwrite" in err
    code, _, err = run_cli(capsys, "qgis-plugin", tmp_path / "plugin.tar")
    assert code == 1 and "must be a .zip path" in err


# ---- inside QGIS ------------------------------------------------------------------------------------
def _qgis_version() -> str | None:
    try:
        done = subprocess.run([QGIS_PYTHON, "-c", "from qgis.core import Qgis; print(Qgis.QGIS_VERSION)"],
                              capture_output=True, text=True, timeout=60, env={**os.environ,
                                                                                "QT_QPA_PLATFORM": "offscreen"})
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def _qml_max(qml: Path) -> float:
    text = qml.read_text()
    return float(text.split('classificationMax="')[1].split('"')[0])


@pytest.mark.slow
def test_headless_qgis(inputs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """predict (T = 4) and buildings from the Processing toolbox of QGIS, and a canceled predict."""
    version = _qgis_version()
    if version is None:
        pytest.skip(f"QGIS is not installed for {QGIS_PYTHON} (apt-get install qgis python3-qgis)")
    code, _, err = run_cli(capsys, "qgis-plugin", tmp_path / "plugin.zip")
    assert code == 0, err
    program = Path(sys.executable).with_name("aerialmtl")
    assert program.is_file(), f"no aerialmtl program beside {sys.executable}"
    (tmp_path / "work").mkdir()
    done = subprocess.run(
        [QGIS_PYTHON, str(REPO / "tests" / "qgis_headless.py"), str(tmp_path / "plugin.zip"), str(program),
         str(inputs["model"]), str(inputs["ortho"]), str(inputs["big"]), str(tmp_path / "work")],
        capture_output=True, text=True, timeout=600, env={**_env(), "QT_QPA_PLATFORM": "offscreen"})
    assert done.returncode == 0, done.stderr[-3000:]
    report: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    print(json.dumps({**{k: report[k] for k in ("qgis", "gdal", "python")},
                      **{f"{k}_s": round(report[k]["seconds"], 1)
                         for k in ("predict", "buildings", "evaluate", "export", "cancel")}}))
    assert report["algorithms"] == sorted(f"aerialmtl:{a}" for a in ALGORITHMS)

    predict, buildings, cancel = report["predict"], report["buildings"], report["cancel"]
    assert "error" not in predict, predict
    assert max(predict["progress"]) == 100.0 and predict["progress"] == sorted(predict["progress"])
    assert "error" not in buildings, buildings
    assert buildings["progress"][-1] == 100.0

    pred = tmp_path / "work" / "pred"
    layers = {layer["name"]: layer for layer in report["layers"]}
    expected = [name for f, name in PREDICTION_LAYERS if (pred / f).is_file()]
    assert len(expected) == 5  # T > 1: height, its spread, classes, entropy, mutual information
    assert [layer["name"] for layer in report["layers"] if layer["group"] == "pred"] == expected
    for filename, name in PREDICTION_LAYERS:
        if name not in layers:
            continue
        layer = layers[name]
        assert layer["valid"] and layer["source"] == str(pred / filename)
        if filename == "classes.tif":  # the class names come from the style, not the GeoTIFF
            assert layer["renderer"] == {"type": "paletted", "classes": ["bare soil", "road", "building", "tree"]}
        else:
            assert layer["renderer"]["type"] == "singlebandpseudocolor" and layer["renderer"]["colors"] == 5
            assert layer["renderer"]["max"] == pytest.approx(_qml_max(pred / filename.replace(".tif", ".qml")))
            unit = {"height.tif": " m", "height_std.tif": " m"}.get(filename, " nats")
            assert layer["renderer"]["legend_suffix"] == unit, (filename, layer["renderer"])  # print layouts
    with rasterio.open(pred / "height.tif") as src:  # the AOI (a memory layer, converted by QGIS) was applied
        height = src.read(1, masked=True)
    assert not height.mask[:, : height.shape[1] // 2 - 2].any() and height.mask[:, height.shape[1] // 2 + 2:].all()
    footprints = layers["buildings (buildings)"]
    assert footprints["valid"] and footprints["features"] >= 1 and footprints["group"] == ""
    assert footprints["renderer"] == {"type": "graduatedSymbol", "field": "height_m", "ranges": 5}

    evaluation, export = report["evaluate"], report["export"]
    assert "error" not in evaluation, evaluation
    assert json.loads((tmp_path / "work" / "report.json").read_text())["height"]["mae"] > 0
    assert "error" not in export, export
    assert (tmp_path / "work" / "height.onnx").stat().st_size > 0
    assert len(report["layers"]) == len(expected) + 1  # evaluate and export add no layer

    tiles = report["tile"]  # a warning of the command reaches the log as a warning
    assert "error" not in tiles, tiles
    assert (tmp_path / "work" / "tiles" / "dataset.yaml").is_file() and tiles["progress"][-1] == 100.0
    assert any("no val/test patch" in w for w in tiles["warnings"]), tiles["warnings"]

    failing = report["failing"]  # the command's own one-line message, as the error and in the log
    assert "missing.pt" in failing["error"] and "\n" not in failing["error"] and "Traceback" not in failing["error"]
    assert failing["errors"].count(failing["error"]) <= 1  # once: raised, not also reported by the plugin
    assert "--model" not in failing["error"]

    assert cancel["error"].startswith("canceled: interrupted; no output was left") and 0 < cancel["canceled_at"] < 100
    assert cancel["left"] in (None, [])  # nothing behind: no folder, or an empty one
    assert not [layer for layer in report["layers"] if "canceled" in layer["source"]]


def _headless_recipe() -> str:
    """The bash block that follows the ``headless-recipe`` marker on the QGIS page, as a reader copies it."""
    page = (REPO / "docs" / "tutorials" / "qgis.md").read_text()
    start = page.index("<!-- headless-recipe")
    block = re.compile(r"```bash\n(.*?)\n```\n", re.S).search(page, start)
    assert block is not None, "no bash block after the headless-recipe marker in docs/tutorials/qgis.md"
    return block.group(1) + "\n"


@pytest.mark.slow
def test_the_headless_recipe_of_the_docs(inputs: dict[str, Path], tmp_path: Path) -> None:
    """The QGIS page's qgis_process recipe, run as written (bash -e) in a fresh QGIS profile: predict, styled layers."""
    if _qgis_version() is None or shutil.which("qgis_process.bin") is None:
        pytest.skip("QGIS is not installed (apt-get install qgis python3-qgis)")
    program = Path(sys.executable).with_name("aerialmtl")
    assert program.is_file(), f"no aerialmtl program beside {sys.executable}"
    work, home = tmp_path / "clone", tmp_path / "home"  # the recipe runs from a clone's root, in a fresh profile
    work.mkdir()
    home.mkdir()
    (work / "samples").symlink_to(REPO / "samples")
    env = {**_env(), "HOME": str(home), "MODEL": str(inputs["model"]),
           "PATH": os.pathsep.join([str(program.parent), os.environ.get("PATH", "")])}
    done = subprocess.run(["bash", "-e", "-c", _headless_recipe()], cwd=work, capture_output=True, text=True,
                          env=env, timeout=900)
    assert done.returncode == 0, (done.stdout[-3000:], done.stderr[-3000:])
    ini = (home / ".local/share/QGIS/QGIS3/profiles/default/QGIS/QGIS3.ini").read_text()
    assert f"Configuration\\AERIALMTL_EXECUTABLE={program}" in ini and "aerialmtl_processing=true" in ini
    assert "LAYERS:" in done.stdout and (work / "maps" / "qgis" / "height.tif").is_file()
    shown = [line for line in done.stdout.splitlines() if ": valid " in line]
    assert "height.tif: valid True, styled True, singlebandpseudocolor, legend in m" in shown, shown
    assert "classes.tif: valid True, styled True, paletted" in shown, shown
    assert len(shown) == 5 and all("valid True, styled True" in line for line in shown), shown


def test_every_predict_setting_is_a_parameter_or_left_out() -> None:
    """Each field of PredictSettings reaches the dialog through its option, or its option is in LEFT_OUT (a tuning
    knob with a sound default): adding a setting is its field, its option and this decision."""
    import dataclasses

    from aerialmtl.inference.settings import PredictSettings

    options = {n: o.opts[0] for o in cli.commands["predict"].params if isinstance(o, click.Option) and o.name
               for n in (o.name, *getattr(o, "library", ()))}
    offered = {p.flag for p in PREDICT.params} | LEFT_OUT["predict"]
    missing = [f.name for f in dataclasses.fields(PredictSettings) if options[f.name] not in offered]
    assert not missing, f"settings neither in the QGIS dialog nor in LEFT_OUT: {missing}"
