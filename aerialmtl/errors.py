"""Exception hierarchy of aerialmtl.

Every error the package raises on purpose descends from :class:`AerialMTLError` and also from the
built-in exception that fits, so callers can catch either. Messages name the argument or file, the
value received and the fix; the CLI prints them on one line without a traceback (unless ``--debug``).
"""

from __future__ import annotations


class AerialMTLError(Exception):
    """Root of all aerialmtl errors."""


class ConfigError(AerialMTLError, ValueError):
    """A YAML config or class scheme is invalid (unknown key, wrong type, bad enum value)."""


class InputError(AerialMTLError, ValueError):
    """An input raster, vector or dataset cannot be used as given."""


class AlignmentError(InputError):
    """Layers cannot be put on one grid (no CRS, no overlap, ...)."""


class LabelError(InputError):
    """A label raster holds codes the class scheme does not declare."""


class CheckpointError(AerialMTLError, ValueError):
    """A checkpoint is missing, corrupt, unsafe or incompatible with the input."""


class OutputExistsError(AerialMTLError, FileExistsError):
    """An output already exists and ``--overwrite`` was not given."""


class OutputError(AerialMTLError, OSError):
    """An output location cannot be written."""
