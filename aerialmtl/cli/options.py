"""How the command line spells the library's parameters: the one table, and the error translation.

Library errors name parameters with marks (``‹tile›``, ``‹overwrite=True›``; see :mod:`aerialmtl.errors`).
The CLI shows them as its options (``--tile``, ``--overwrite``) through :data:`FLAGS` and the per-command
differences in :data:`COMMAND_FLAGS`. An error about one option's value (:attr:`AerialMTLError.param`)
becomes click's usage error for that option (exit code 2, usage line, ``Invalid value for --tile: ...``),
so the CLI does not validate again what the library already checks.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import click

from aerialmtl.errors import PARAM_MARK, AerialMTLError, ConfigError, InputError

#: Library parameter → option, for every command (the same name means the same thing everywhere).
FLAGS: dict[str, str] = {
    "aoi": "--aoi",
    "bands": "--bands",
    "batch_size": "--batch-size",
    "class_field": "--class-field",
    "classes": "--classes",
    "device": "--device",
    "dsm": "--dsm",
    "dtm": "--dtm",
    "gsd": "--gsd",
    "height_threshold": "--height-threshold",
    "ignore_unknown_codes": "--ignore-unknown-codes",
    "labels": "--labels",
    "labels_vector": "--labels-vector",
    "max_height": "--max-height",
    "max_steps": "--max-steps",
    "max_time_s": "--max-time",
    "mc": "--mc",
    "min_valid": "--min-valid",
    "ndsm": "--ndsm",
    "out": "--out",
    "out_dir": "--out",
    "overlap": "--overlap",
    "overwrite": "--overwrite",
    "precision": "--precision",
    "probabilities": "--probabilities",
    "resume": "--resume",
    "sample_size": "--sample-size",
    "size": "--size",
    "split_block": "--split-block",
    "split_ratios": "--split-ratios",
    "stride": "--stride",
    "tile": "--tile",
    "z_unit": "--z-unit",
}

#: Per command: parameters spelled differently from :data:`FLAGS` (or only there).
COMMAND_FLAGS: dict[str, dict[str, str]] = {
    "tile": {"ortho": "--ortho", "block_size": "--split-block", "ratios": "--split-ratios", "aoi": "--split-aoi"},
    "train": {"data_dir": "--data", "config": "--config"},
    "predict": {"checkpoint": "--model", "ortho": "ORTHOS"},
    "evaluate": {"pred_dir": "--pred", "height_ref": "--height", "labels_ref": "--labels", "dsm_ref": "--dsm",
                 "dtm_ref": "--dtm"},
    "synth": {"out_dir": "OUT"},
}


def flags_for(command: str | None) -> dict[str, str]:
    """The parameter → option table of ``command`` (:data:`FLAGS` when unknown)."""
    return {**FLAGS, **COMMAND_FLAGS.get(command or "", {})}


F = TypeVar("F", bound=Callable[..., Any])


def usage_errors(command: str, callback: F) -> F:
    """Wrap a command's callback: a library error about one option's value becomes click's usage error.

    The message is spelled with the command's options; a leading mark of the option itself is dropped
    (click already says ``Invalid value for --tile:``).
    """
    flags = flags_for(command)

    @functools.wraps(callback)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return callback(*args, **kwargs)
        except (InputError, ConfigError) as exc:
            option = flags.get(exc.param or "")
            if option is None or not option.startswith("-"):
                raise
            text = exc.message
            lead = PARAM_MARK.match(text)
            if lead is not None and lead.group(1) == exc.param and lead.group(2) is None:
                text = text[lead.end():].lstrip()
            raise click.BadParameter(AerialMTLError(text).render(flags), param_hint=option) from exc

    return wrapper  # type: ignore[return-value]


__all__ = ["COMMAND_FLAGS", "FLAGS", "flags_for", "usage_errors"]
