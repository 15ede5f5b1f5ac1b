"""Exception hierarchy of aerialmtl, and how messages name parameters.

Every error the package raises on purpose descends from :class:`AerialMTLError` and also from the
built-in exception that fits, so callers can catch either. Messages name the argument or file, the
value received and the fix; the CLI prints them on one line without a traceback (unless ``--debug``).

A message names a parameter of the library in neutral words with a mark, ``‹name›`` or ``‹name=value›``
(e.g. ``"‹tile› must be a multiple of 32 pixels, got 100; pass e.g. ‹tile=512›"``). Read from Python the
marks are plain names (``tile``, ``tile=512``: :meth:`AerialMTLError.__str__`); the command line shows
its own options instead (``--tile``, ``--tile 512``), through one table per command
(:mod:`aerialmtl.cli.options`) and :meth:`AerialMTLError.render`. An error about one parameter's value
carries its name in :attr:`AerialMTLError.param`, so the CLI can report it as a usage error of that option.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

#: A parameter mark in a message: ``‹name›`` or ``‹name=value›``.
PARAM_MARK = re.compile(r"‹([A-Za-z_][A-Za-z0-9_]*)(?:=([^›]*))?›")


def render(message: str, flags: Mapping[str, str] | None = None) -> str:
    """``message`` with its parameter marks spelled for the reader.

    Args:
        message: text with ``‹name›`` / ``‹name=value›`` marks.
        flags: parameter name → command-line option (``{"tile": "--tile"}``); ``None`` spells the marks
            as Python names. A parameter missing from ``flags`` keeps its Python spelling.

    Returns:
        ``‹tile›`` → ``tile`` / ``--tile``; ``‹tile=512›`` → ``tile=512`` / ``--tile 512``;
        ``‹overwrite=True›`` → ``overwrite=True`` / ``--overwrite`` (a flag option takes no value).
    """

    def spell(match: re.Match[str]) -> str:
        name, value = match.group(1), match.group(2)
        option = flags.get(name) if flags is not None else None
        if option is None:
            return name if value is None else f"{name}={value}"
        if value is None or value == "True":
            return option
        return f"{option} {value}"

    return PARAM_MARK.sub(spell, message)


#: Where a sentence ends inside a message from a library (GDAL, OpenVINO, torch).
_SENTENCE_END = re.compile(r"(?<=[.;!?])\s+")


def cause(exc: BaseException | str | None, limit: int = 240) -> str:
    """``exc``'s text on one line, for the parenthesis of a message, in whole sentences.

    As many of its sentences as fit in ``limit`` characters, and always the first one whole (a library's sentence
    is never cut mid-word: "You can disable this check by defining the CHECK_DISK_FREE_SPACE configuration option
    to FALSE." stays whole). An exception with no text gives its class name.
    """
    if exc is None:
        return ""
    text = " ".join(str(exc).split())
    if not text:
        return exc.__class__.__name__ if isinstance(exc, BaseException) else ""
    if len(text) <= limit:
        return text
    out = ""
    for sentence in _SENTENCE_END.split(text):
        if out and len(out) + 1 + len(sentence) > limit:
            return out + " ..."
        out = f"{out} {sentence}" if out else sentence
    return out


class AerialMTLError(Exception):
    """Root of all aerialmtl errors.

    Args:
        message: the message, parameters marked as ``‹name›`` / ``‹name=value›`` (see the module docstring).
        param: the parameter whose value is wrong, when the error is about one parameter's value
            (``"a/b"``: two parameters that cannot be given together).
    """

    def __init__(self, message: str = "", *, param: str | None = None) -> None:
        super().__init__(message)
        self.param = param

    @property
    def message(self) -> str:
        """The message with its parameter marks (see :func:`render`)."""
        return str(self.args[0]) if self.args else ""

    def render(self, flags: Mapping[str, str] | None = None) -> str:
        """The message spelled with ``flags`` (parameter → option), see :func:`render`."""
        return render(self.message, flags)

    def __str__(self) -> str:
        return self.render(None)


class ConfigError(AerialMTLError, ValueError):
    """A YAML config or class scheme is invalid (unknown key, wrong type, bad enum value)."""


class InputError(AerialMTLError, ValueError):
    """An input raster, vector, dataset or argument value cannot be used as given."""


class AlignmentError(InputError):
    """Layers cannot be put on one grid (no CRS, no overlap, ...)."""


class LabelError(InputError):
    """A label raster holds codes the class scheme does not declare."""


class CheckpointError(AerialMTLError, ValueError):
    """A checkpoint is missing, corrupt, unsafe or incompatible with the input."""


class NonFiniteError(AerialMTLError, FloatingPointError):
    """Numbers that can only be garbage.

    A diverged training (NaN/inf loss or score), a checkpoint with NaN/inf weights, or a model that gives NaN/inf
    for valid inputs.
    """


class OutputExistsError(AerialMTLError, FileExistsError):
    """An output already exists and ``overwrite`` was not given."""


class OutputError(AerialMTLError, OSError):
    """An output location cannot be written."""


class OutputInUseError(OutputError):
    """Another process is writing the same output folder (it holds the folder's lock)."""


class PeerFailure(AerialMTLError, RuntimeError):
    """Another process of a multi-process (torchrun) run failed or was stopped, or an input failed on another rank.

    The message names the process or the input and the cause.
    """


__all__ = [
    "PARAM_MARK", "AerialMTLError", "AlignmentError", "CheckpointError", "ConfigError", "InputError", "LabelError",
    "NonFiniteError", "OutputError", "OutputExistsError", "OutputInUseError", "PeerFailure", "cause", "render",
]
