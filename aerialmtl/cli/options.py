"""Options shared by the commands, defined once, and how the command line spells the library's parameters.

**Shared options.** Options that several commands take (``--overwrite``, ``--quiet``, ``--device``,
``--precision``, ``--compile``, raster inputs that may be URLs) are decorators defined here and used by
every command (as rasterio's ``rio/options.py`` does), so they mean and read the same everywhere.
Raster inputs are GDAL paths (:mod:`aerialmtl.io.paths`): local files, VRTs, ``https://``, ``s3://``,
``/vsicurl/``, ``/vsizip/``; they reach the library as strings, never as ``pathlib.Path`` (which folds
``s3://b/x`` into ``s3:/b/x``).

**Parameter → option table.** Library errors name parameters with marks (``‹tile›``, ``‹overwrite=True›``;
see :mod:`aerialmtl.errors`). The CLI shows them as its options (``--tile``, ``--overwrite``) through a table
derived from the commands themselves (:func:`flags_for`): each option stands for the parameter of its own
name, plus the library parameters it lists in ``library=`` when the CLI spells them otherwise (``--model``
is the library's ``checkpoint``). An error about one option's value (:attr:`AerialMTLError.param`) becomes
click's usage error for that option (exit code 2, usage line, ``Invalid value for --tile: ...``), so the
CLI does not validate again what the library already checks.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import click

from aerialmtl.errors import PARAM_MARK, AerialMTLError, ConfigError, InputError
from aerialmtl.inference.engines.names import ENGINE_MODULES
from aerialmtl.io.paths import gdal_path, is_local

F = TypeVar("F", bound=Callable[..., Any])
P = ParamSpec("P")
R = TypeVar("R")
Decorator = Callable[[F], F]


# ---- parameters that name the library parameters they stand for ------------------------------------
def _names(library: str | Sequence[str]) -> tuple[str, ...]:
    return (library,) if isinstance(library, str) else tuple(library)


class LibraryOption(click.Option):
    """A click option that also stands for library parameters of other names (``library=``)."""

    def __init__(self, *args: Any, library: str | Sequence[str] = (), **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.library = _names(library)


class LibraryArgument(click.Argument):
    """A click argument that also stands for library parameters of other names (``library=``)."""

    def __init__(self, *args: Any, library: str | Sequence[str] = (), **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.library = _names(library)


def option(*decls: str, library: str | Sequence[str] = (), **kwargs: Any) -> Decorator[Any]:
    """``click.option`` whose option also stands for the library parameters ``library``."""
    return click.option(*decls, cls=LibraryOption, library=library, **kwargs)


def argument(*decls: str, library: str | Sequence[str] = (), **kwargs: Any) -> Decorator[Any]:
    """``click.argument`` whose argument also stands for the library parameters ``library``."""
    return click.argument(*decls, cls=LibraryArgument, library=library, **kwargs)


# ---- raster inputs ---------------------------------------------------------------------------------
class RasterPath(click.ParamType):  # type: ignore[type-arg]  # generic only in click's stubs
    """A raster GDAL can open: a local file (checked to exist), a URL or a ``/vsi...`` path (a string)."""

    name = "raster"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        """The GDAL path of ``value`` (URLs as ``/vsi...`` paths); a local path must be an existing file."""
        path = gdal_path(value)
        if is_local(path):
            p = Path(path)
            if not p.exists():
                self.fail(f"'{value}' does not exist; give a raster file, a URL (https://..., s3://...) or a GDAL "
                          "/vsi... path", param, ctx)
            if p.is_dir():
                self.fail(f"'{value}' is a folder; give a raster file (GeoTIFF, VRT, ...)", param, ctx)
        return path


#: The type of every raster input (see :class:`RasterPath`).
RASTER = RasterPath()
_RASTER_HELP = " A file, VRT, URL (https://, s3://) or GDAL /vsi... path."


def raster_option(*decls: str, help: str = "", library: str | Sequence[str] = (), **kwargs: Any) -> Decorator[Any]:
    """An option naming an input raster that may live anywhere GDAL reads (see :class:`RasterPath`)."""
    return option(*decls, type=RASTER, help=help + _RASTER_HELP, library=library, **kwargs)


def raster_argument(name: str, library: str | Sequence[str] = (), **kwargs: Any) -> Decorator[Any]:
    """An argument naming input rasters that may live anywhere GDAL reads (see :class:`RasterPath`)."""
    return argument(name, type=RASTER, library=library, **kwargs)


# ---- outputs ---------------------------------------------------------------------------------------
class OutputPath(click.Path):
    """A local output path (``click.Path`` → ``pathlib.Path``).

    A URL or a GDAL ``/vsi...`` path is refused before ``pathlib`` folds ``s3://b/x`` into a local folder ``s3:/b/x``.
    """

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        """``value`` unchanged if it is a local path; a URL or a GDAL virtual path is refused."""
        if isinstance(value, str) and not is_local(value):
            self.fail(f"outputs must be local, but '{value}' is a URL or GDAL virtual path; write to a local folder "
                      "and copy it up afterwards (e.g. `aws s3 sync FOLDER s3://bucket/prefix`)", param, ctx)
        return super().convert(value, param, ctx)


def output_path(*, file_okay: bool = True, dir_okay: bool = True) -> OutputPath:
    """The type of every output option (``--out``): a local :class:`pathlib.Path` (see :class:`OutputPath`)."""
    return OutputPath(file_okay=file_okay, dir_okay=dir_okay, path_type=Path)


# ---- options shared by several commands --------------------------------------------------------------
def overwrite_option(help: str = "Replace existing outputs.") -> Decorator[Any]:
    """``--overwrite``: replace what the command wrote before (each command says what in ``help``)."""
    return option("--overwrite", is_flag=True, help=help)


def quiet_option() -> Decorator[Any]:
    """``--quiet``: no progress bar."""
    return option("--quiet", is_flag=True, help="No progress bar.")


DEVICES = ("auto", "cpu", "cuda")
PRECISIONS = ("auto", "bf16", "fp32")


def device_option(default: str | None = "auto",
                  help: str = "auto = the GPU when there is one; under torchrun, each process uses GPU LOCAL_RANK."
                  ) -> Decorator[Any]:
    """``--device auto|cpu|cuda`` (``default=None``: the command's config decides)."""
    return option("--device", type=click.Choice(DEVICES), default=default, show_default=default is not None,
                  help=help)


def precision_option(default: str | None = "auto",
                     help: str = "auto = bf16 autocast on CUDA, fp32 on CPU (CPUs without bf16 units run bf16 "
                                 "far slower).") -> Decorator[Any]:
    """``--precision auto|bf16|fp32`` (``default=None``: the command's config decides)."""
    return option("--precision", type=click.Choice(PRECISIONS), default=default, show_default=default is not None,
                  help=help)


def compile_option(dest: str = "compile_") -> Decorator[Any]:
    """``--compile``: torch.compile the model, falling back to the plain model with a warning."""
    return option("--compile", dest, is_flag=True, library="compile",
                  help="torch.compile the model (a warning and the plain model where compiling is unavailable).")


class EngineName(click.Choice):  # type: ignore[type-arg]  # generic only in click's stubs
    """``auto`` or a name of the engine registry (:data:`aerialmtl.inference.engines.names.ENGINE_MODULES`).

    The names are read from that table (which imports no engine, so no torch) each time the choices are shown or
    checked.
    """

    name = "engine"

    def __init__(self) -> None:
        super().__init__(("auto",))

    @property
    def choices(self) -> tuple[str, ...]:
        """``auto`` and the registry's engines."""
        return ("auto", *ENGINE_MODULES)

    @choices.setter
    def choices(self, value: Sequence[str]) -> None:
        """The registry decides; click's own assignment is ignored."""


# ---- the parameter → option table, derived from the commands -------------------------------------------
def _spelling(param: click.Parameter) -> str:
    """How the command line shows ``param``: its long option (``--tile``) or its metavar (``ORTHOS``)."""
    if isinstance(param, click.Option):
        longs = [o for o in param.opts if o.startswith("--")]
        return longs[0] if longs else param.opts[0]
    return param.human_readable_name


def command_flags(command: click.Command) -> dict[str, str]:
    """Parameter name → option of ``command``: each parameter's own name and its ``library`` names."""
    table: dict[str, str] = {}
    for param in command.params:
        if param.name is None or param.name == "help":
            continue
        spelled = _spelling(param)
        for name in (param.name, *getattr(param, "library", ())):
            table.setdefault(name, spelled)
    return table


def values_for(names: Iterable[Any], values: dict[str, Any]) -> dict[str, Any]:
    """The values of the running command's options for the library parameters ``names``.

    ``values``: what click passed, by parameter name; ``names``: names, or dataclass fields; each found as
    :func:`command_flags` finds them.

    Raises:
        TypeError: a name no option of the command stands for (the command lacks an option: a programming error).
    """
    params = click.get_current_context().command.params
    source = {n: p.name for p in params if p.name is not None for n in (p.name, *getattr(p, "library", ()))}
    wanted = [getattr(n, "name", n) for n in names]
    missing = [n for n in wanted if n not in source]
    if missing:
        raise TypeError(f"the command has no option for {', '.join(missing)}: add one (docs/CONTRACTS.md)")
    return {n: values[source[n]] for n in wanted}


def _commands() -> dict[str, click.Command]:
    from aerialmtl.cli import cli  # cycle: aerialmtl.cli imports this module to build the group

    return dict(cli.commands)


def common_flags() -> dict[str, str]:
    """The table outside a command: each parameter as the commands that have it spell it.

    Where commands differ (``aoi`` is ``--aoi`` in predict, ``--split-aoi`` in tile), the option named after
    the parameter wins, else the spelling most commands use.
    """
    seen: dict[str, list[str]] = {}
    for command in _commands().values():
        for name, flag in command_flags(command).items():
            seen.setdefault(name, []).append(flag)
    table = {}
    for name, flags in sorted(seen.items()):
        own = "--" + name.replace("_", "-")
        table[name] = own if own in flags else max(sorted(set(flags)), key=flags.count)
    return table


def flags_for(command: str | click.Command | None) -> dict[str, str]:
    """The parameter → option table of ``command`` (:func:`common_flags` for what it lacks, or when unknown)."""
    if isinstance(command, str):
        command = _commands().get(command)
    table = common_flags()
    if command is not None:
        table.update(command_flags(command))
    return table


def __getattr__(name: str) -> dict[str, str]:
    if name == "FLAGS":  # the table outside any command, derived on use (the commands import this module)
        return common_flags()
    raise AttributeError(name)


def usage_errors(command: str, callback: Callable[P, R]) -> Callable[P, R]:
    """Wrap a command's callback: a library error about one option's value becomes click's usage error.

    The message is spelled with the command's options; a leading mark of the option itself is dropped
    (click already says ``Invalid value for --tile:``). An error about two options given together
    (``param="resume/init"``) names both (``Invalid value for --resume/--init:``).
    """

    @functools.wraps(callback)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return callback(*args, **kwargs)
        except (InputError, ConfigError) as exc:
            flags = flags_for(command)
            options = [flags.get(name) for name in (exc.param or "").split("/")]
            if not all(o is not None and o.startswith("-") for o in options):
                raise
            option = "/".join(o for o in options if o is not None)
            text = exc.message
            lead = PARAM_MARK.match(text)
            if lead is not None and lead.group(1) == exc.param and lead.group(2) is None:
                text = text[lead.end():].lstrip()
            raise click.BadParameter(AerialMTLError(text).render(flags), param_hint=option) from exc

    return wrapper


__all__ = [
    "DEVICES", "PRECISIONS", "RASTER", "EngineName", "LibraryArgument", "LibraryOption", "OutputPath", "RasterPath",
    "argument", "command_flags", "common_flags", "compile_option", "device_option", "flags_for", "option",
    "output_path", "overwrite_option", "precision_option", "quiet_option", "raster_argument", "raster_option",
    "usage_errors", "values_for",
]
