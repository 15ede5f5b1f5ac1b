"""The ``aerialmtl`` command line: a thin click group over the library.

Every command module defines one click command; this module registers them and turns expected
errors (:class:`~aerialmtl.errors.AerialMTLError`, unreadable rasters, unwritable folders) into a
one-line message on stderr with exit code 1. ``--debug`` shows the traceback instead.

Answers that compute nothing (``--help`` of the group and of every command, ``--version``, shell completion)
import neither torch, OpenVINO, numba nor rasterio: the command modules import their library inside the
command's function, and GDAL's libtiff is quietened only when a command runs (tests/test_cli_imports.py).
"""

from __future__ import annotations

import functools
import gc
import importlib
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

# Process settings read once by torch's allocator and its OpenMP runtime, so set before anything imports
# torch (a user's own setting wins; bench/RESULTS.md, predict, has the measurements):
# - large CPU tensors on transparent huge pages: on VMs a fresh 4 KiB page fault costs microseconds, and
#   predict allocates model activations of tens of MiB per window;
# - OpenMP threads that sleep instead of spinning between parallel regions: predict runs reader, writer
#   and COG threads beside torch's, and on a busy machine spinning threads wait for descheduled ones
#   (3-4x slower on 2 shared cores).
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import click

from aerialmtl import progress, stores
from aerialmtl._version import __version__
from aerialmtl.cli.bench import bench
from aerialmtl.cli.buildings import buildings
from aerialmtl.cli.cache import cache
from aerialmtl.cli.demo import demo
from aerialmtl.cli.evaluate import evaluate
from aerialmtl.cli.export import export
from aerialmtl.cli.options import flags_for, usage_errors
from aerialmtl.cli.predict import predict
from aerialmtl.cli.pretrain import pretrain
from aerialmtl.cli.qgis_plugin import qgis_plugin
from aerialmtl.cli.synth import synth
from aerialmtl.cli.tile import tile
from aerialmtl.cli.train import train
from aerialmtl.errors import AerialMTLError
from aerialmtl.signals import stop_signal, stop_signals


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="aerialmtl")
@click.option("--debug", is_flag=True, help="Show full tracebacks instead of one-line errors.")
@click.option("--progress", "progress_mode", type=click.Choice(progress.MODES), default="bar", show_default=True,
              envvar=progress.PROGRESS_ENV, show_envvar=True,
              help="How commands report progress on stderr: tqdm bars, or one JSON line per step "
                   '({"stage", "done", "total", "unit"}) for programs that run aerialmtl (the QGIS plugin).')
@click.pass_context
def cli(ctx: click.Context, debug: bool, progress_mode: str) -> None:
    """Height (nDSM) and land-cover maps with MC-dropout uncertainty from aerial orthophotos."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug
    progress.set_mode(progress_mode)


#: Whether a command quietens libtiff before it runs (set by :func:`main` unless ``--debug``).
_quiet_libtiff = False

#: The library each command that computes imports when it runs (torch, OpenVINO's bindings, GDAL), loaded by
#: :func:`_prepared` before the command's own function so that they are frozen out of the garbage collector's sight.
LIBRARIES: dict[str, tuple[str, ...]] = {
    "predict": ("aerialmtl.inference.jobs",),
    "train": ("aerialmtl.training.loop",),
    "pretrain": ("aerialmtl.training.pretrain",),
    "evaluate": ("aerialmtl.evaluation.evaluate",),
    "tile": ("aerialmtl.tiling.tile",),
    "buildings": ("aerialmtl.buildings",),
    "export": ("aerialmtl.inference.export",),
    "demo": ("aerialmtl.demo",),
    "synth": ("aerialmtl.data.synth",),
    "bench": ("aerialmtl.inference.cpu_bench", "aerialmtl.inference.runner"),
}


def _prepared(name: str, callback: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap command ``name``'s callback: import its library (:data:`LIBRARIES`) and quieten libtiff only once the
    command runs (never for ``--help``, ``--version`` or completion).

    The imports run with Python's cyclic garbage collector paused, and what they made (about a million objects
    that live as long as the process) is then moved out of its sight (:func:`gc.freeze`): walking them again in
    every full collection during a run and at exit cost ~0.5 s of a 2.2 s warm ``predict`` (bench/RESULTS.md,
    issue 27). Objects made by the command itself are collected as usual.
    """

    @functools.wraps(callback)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        enabled = gc.isenabled()
        gc.disable()
        try:
            for module in LIBRARIES.get(name, ()):
                importlib.import_module(module)
            if _quiet_libtiff:
                quiet_libtiff()
        finally:
            gc.freeze()
            if enabled:
                gc.enable()
        return callback(*args, **kwargs)

    return wrapper


for _command in (synth, tile, train, pretrain, predict, evaluate, buildings, export, qgis_plugin, demo, bench,
                 cache):
    assert _command.name is not None and _command.callback is not None
    _command.callback = usage_errors(_command.name, _prepared(_command.name, _command.callback))
    cli.add_command(_command)


def _one_line(exc: BaseException, flags: dict[str, str] | None = None) -> str:
    """``exc`` as one line; aerialmtl errors with their parameters spelled as ``flags`` (options)."""
    text = exc.render(flags) if isinstance(exc, AerialMTLError) else str(exc)
    text = " ".join(text.split()) or exc.__class__.__name__
    seen = exc.__cause__ or exc.__context__
    while "See previous exception" in text and seen is not None:  # rasterio's own words point at GDAL's: show them
        text = f"{text} ({' '.join(str(seen).split()) or seen.__class__.__name__})"
        seen = seen.__cause__ or seen.__context__
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:  # one of several torchrun processes: say which
        text = f"[rank {os.environ.get('RANK', '?')}] {text}"
    return text


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: object = None, line: str | None = None) -> None:
    """Print a warning as one ``warning: ...`` line on stderr (no source location, no code line), on a line of its
    own while a progress bar is on screen (:func:`aerialmtl.progress.above_bars`).
    """
    with progress.above_bars():
        click.echo(f"warning: {' '.join(str(message).split())}", err=True)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point: run the group, mapping expected errors to exit code 1.

    Exit codes: 0 success; 1 an error with a one-line message on stderr (naming the file or option,
    the value and the fix); 2 a usage error (click's message); 130 interrupted (Ctrl-C), 143 stopped by
    SIGTERM, 129 by SIGHUP (both handled like Ctrl-C, :mod:`aerialmtl.signals`). Warnings
    (documented fallbacks) are printed as one ``warning:`` line each. ``--debug`` shows tracebacks
    and Python's own warning format instead.
    """
    global _quiet_libtiff
    args = sys.argv[1:] if argv is None else argv
    debug = "--debug" in args
    stores.reset_warnings()  # each command warns once about each store problem it meets
    with warnings.catch_warnings(), stop_signals():
        if not debug:
            warnings.showwarning = _show_warning
            # libraries' deprecation notices are for developers; a user can act on neither
            for category in (DeprecationWarning, PendingDeprecationWarning):
                warnings.filterwarnings("ignore", category=category)
        mode, quiet = progress.get_mode(), _quiet_libtiff
        _quiet_libtiff = not debug  # done by the command itself when it runs (--help never loads GDAL)
        try:
            _run(args, debug)
        finally:  # --progress holds for this command only (the tests call main() many times in one process)
            progress.set_mode(mode)
            _quiet_libtiff = quiet


def quiet_libtiff() -> None:
    """Stop libtiff's global default handlers from printing raw lines on stderr (``_tiffWriteProc: No space left on
    device.`` above the one-line error). GDAL reports the same failures itself (a failed write becomes the
    error the command turns into its one line); ``--debug`` keeps libtiff's lines. Linux only (the loaded
    libtiff is found in ``/proc/self/maps``); elsewhere nothing changes.
    """
    import ctypes

    import rasterio  # noqa: F401 - loads GDAL and its libtiff

    try:
        maps = Path("/proc/self/maps").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return
    libs = {line.split()[-1] for line in maps.splitlines() if "libtiff" in line and line.split()[-1].startswith("/")}
    for lib in libs:
        try:
            handle = ctypes.CDLL(lib)
            handle.TIFFSetErrorHandler(None)
            handle.TIFFSetWarningHandler(None)
        except (OSError, AttributeError):
            continue


def _command_name(args: list[str]) -> str | None:
    """The sub-command named in ``args`` (``None`` when there is none)."""
    return next((a for a in args if a in cli.commands), None)


def _interrupted(args: list[str], exc: BaseException | None = None) -> None:
    """Say what an interrupted command left behind and how to finish; exit 128 + the signal (130 for Ctrl-C).

    SIGTERM and SIGHUP (:mod:`aerialmtl.signals`) get the same message as Ctrl-C.
    """
    command = _command_name(args)
    code = 128 + stop_signal(exc)
    if command == "train":
        click.echo("Error: interrupted; checkpoints are only ever replaced whole: continue from the run's last.pt "
                   "with `aerialmtl train --out RUN --resume`, or start again with --overwrite", err=True)
    elif command in ("predict", "tile"):
        click.echo("Error: interrupted; no output was left at a final path. Re-run the command to finish.", err=True)
    else:
        click.echo("Error: interrupted; files are only ever written whole: re-run the command (with --overwrite "
                   "if it reports outputs that exist)", err=True)
    sys.exit(code)


def _is_raster_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a rasterio error (looked up only if rasterio was imported: none is raised else)."""
    errors = sys.modules.get("rasterio.errors")
    return errors is not None and isinstance(exc, errors.RasterioError)


def _expected(exc: BaseException, args: list[str]) -> None:
    """Report an expected error (aerialmtl's, rasterio's, the operating system's) as one line; exit 1."""
    hint = "" if isinstance(exc, AerialMTLError) else " (run with --debug for the traceback)"
    click.echo(f"Error: {_one_line(exc, flags_for(_command_name(args)))}{hint}", err=True)
    sys.exit(1)


def _run(args: list[str], debug: bool) -> None:
    try:
        cli.main(args=args, prog_name="aerialmtl", standalone_mode=False)
    except click.exceptions.Abort as exc:  # click turns Ctrl-C (KeyboardInterrupt) into Abort
        if debug:
            raise
        if isinstance(exc.__context__, KeyboardInterrupt):
            _interrupted(args, exc.__context__)
        click.echo("Aborted.", err=True)
        sys.exit(130)
    except click.ClickException as exc:  # usage errors → exit 2 (click's own formatting)
        exc.show()
        sys.exit(exc.exit_code)
    except KeyboardInterrupt as exc:
        if debug:
            raise
        _interrupted(args, exc)
    except (AerialMTLError, OSError) as exc:
        if debug:
            raise
        _expected(exc, args)
    except Exception as exc:  # a bug: still one line, and the way to get the details
        if debug:
            raise
        if _is_raster_error(exc):
            _expected(exc, args)
        click.echo(f"Error: unexpected {exc.__class__.__name__}: {_one_line(exc)[:300]}; run again with "
                   "`aerialmtl --debug ...` for the traceback and report it", err=True)
        sys.exit(1)
