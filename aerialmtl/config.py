"""Load YAML into (frozen) dataclasses, validating once with messages that name the bad key.

Usage::

    @dataclass(frozen=True)
    class Optim:
        lr: float = 2e-4
        kind: Literal["adam", "sgd"] = "adam"

    cfg = load_yaml_config("train.yaml", TrainConfig)      # or from_dict(TrainConfig, data)

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``, ``Optional[T]`` /
``T | None``, ``list[T]``, ``tuple[T, ...]``, ``tuple[A, B]``, ``dict[str, T]``, nested dataclasses
and ``Any``. Unknown keys, wrong types and bad enum values raise :class:`ConfigError` naming the
key path (``train.optim.lr``) and the valid keys or choices. Floats must be finite (YAML's ``.nan`` and
``.inf`` are refused with the key path); ranges are checked by each dataclass's ``__post_init__``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import warnings
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from aerialmtl.errors import ConfigError

T = TypeVar("T")


def _describe(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


def _did_you_mean(value: Any, choices: list[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest choice to a typo, or an empty string."""
    close = difflib.get_close_matches(str(value), choices, n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _convert(tp: Any, value: Any, path: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert it (lists → tuples, dicts → dataclasses)."""
    where = path or "<root>"
    if tp is Any:
        return value
    origin = get_origin(tp)
    args = get_args(tp)
    if origin is Union or (hasattr(types, "UnionType") and origin is types.UnionType):
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        errors = []
        for a in non_none:
            try:
                return _convert(a, value, path)
            except ConfigError as exc:  # try the next alternative
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(non_none) == 1 else
                          f"{where}: got {value!r}; expected {' or '.join(_describe(a) for a in args)}")
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{where}: got {value!r}; valid choices are {', '.join(repr(a) for a in args)}"
                              + _did_you_mean(value, [str(a) for a in args]))
        return value
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping of keys for {tp.__name__}, got {value!r}")
        return from_dict(tp, value, path)
    if origin in (list, tuple) or tp in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected a list of {len(args)} items, got {len(value)}")
            return tuple(_convert(a, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        items = [_convert(item, v, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if (origin is tuple or tp is tuple) else items
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        vt = args[1] if len(args) == 2 else Any
        return {k: _convert(vt, v, f"{path}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):  # YAML's .nan / .inf: no setting of this package means them
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise ConfigError(f"{where}: expected a file path, got {value!r}")
        return Path(value)
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{where}: expected {_describe(tp)}, got {value!r}")
    return value


def from_dict(cls: type[T], data: dict[str, Any] | None, path: str = "") -> T:
    """Build dataclass ``cls`` from a plain mapping, validating every key and value.

    Args:
        cls: the dataclass type.
        data: mapping from YAML (``None`` means all defaults).
        path: key path of ``data`` inside the whole document, used in messages.

    Raises:
        ConfigError: unknown key, missing required key, wrong type or bad choice; the message names
            the key path and the valid keys/choices.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{path or '<root>'}: expected a mapping, got {data!r}")
    removed: dict[str, str] = getattr(cls, "REMOVED_KEYS", {})  # key → why it is read and ignored
    for key in [k for k in data if k in removed]:
        warnings.warn(f"'{f'{path}.{key}' if path else key}' is ignored: {removed[key]}; remove it from the file",
                      FutureWarning, stacklevel=3)
        data = {k: v for k, v in data.items() if k != key}
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = f"{path}.{unknown[0]}" if path else str(unknown[0])
        raise ConfigError(f"unknown key '{key}'; valid keys here are: {', '.join(sorted(fields))}"
                          + _did_you_mean(unknown[0], list(fields)))
    kwargs = {}
    for name, f in fields.items():
        sub = f"{path}.{name}" if path else name
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], sub)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"missing required key '{sub}'")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{path or cls.__name__}: {exc}") from exc


def to_dict(obj: Any) -> Any:
    """Dataclass (nested) → plain dicts/lists/scalars, safe for YAML and ``torch.save(weights_only)``."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    return obj


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader reading floats as YAML 1.2 does: ``1e-4`` and ``1e3`` are numbers (YAML 1.1, which
    PyYAML follows, wants a dot and a signed exponent, so ``lr: 1e-4`` would be the string ``'1e-4'``).
    """


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"""),
    list("-+0123456789"),
)


def read_yaml(path: str | Path) -> Any:
    """Parse a YAML file with a message naming the file on failure."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file '{p}' does not exist; pass the path of a YAML file")
    try:
        with p.open("r", encoding="utf-8") as fh:
            return yaml.load(fh, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file '{p}' is not valid YAML: {exc}") from exc


def load_yaml_config(path: str | Path, cls: type[T]) -> T:
    """Read YAML file ``path`` into dataclass ``cls`` (see :func:`from_dict`); errors name the file."""
    data = read_yaml(path)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


__all__ = ["from_dict", "to_dict", "read_yaml", "load_yaml_config"]
