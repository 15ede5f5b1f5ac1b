"""Load YAML into (frozen) dataclasses, validating once with messages that name the bad key.

Usage::

    @dataclass(frozen=True)
    class Optim:
        lr: float = 2e-4
        kind: Literal["adam", "sgd"] = "adam"

    cfg = load_yaml_config("train.yaml", TrainConfig)      # or from_dict(TrainConfig, data)

Validation is pydantic's (the package's one validation system: the files aerialmtl writes, ``prediction.json``,
the checkpoint's metadata, ``train_state`` and calibration, go through it too), in strict mode over the frozen
dataclasses. Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``, ``Optional[T]`` /
``T | None``, ``list[T]``, ``tuple[T, ...]``, ``tuple[A, B]``, ``dict[str, T]``, nested dataclasses
and ``Any``. Unknown keys, wrong types and bad enum values raise :class:`ConfigError` naming the
key path (``train.optim.lr``) and the valid keys or choices. Floats must be finite (YAML's ``.nan`` and
``.inf`` are refused with the key path); ranges are checked by each dataclass's ``__post_init__``.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import re
import types
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml
from pydantic import ConfigDict, TypeAdapter, ValidationError

from aerialmtl.errors import AerialMTLError, ConfigError

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


#: How every dataclass is validated (pydantic, the package's one validation system): no unknown keys, no type
#: coercion beyond what YAML and JSON cannot say (a list for a tuple, a string for a path, an integer for a
#: float), no NaN or infinity.
_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


def _configure(tp: Any, seen: set[Any]) -> None:
    """Give every dataclass reachable from annotation ``tp`` the strict validation config (:data:`_STRICT`)."""
    if tp in seen:
        return
    seen.add(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if "__pydantic_config__" not in tp.__dict__:
            tp.__pydantic_config__ = _STRICT  # type: ignore[attr-defined]  # pydantic's per-class hook; `type` declares none
        for hint in get_type_hints(tp).values():
            _configure(hint, seen)
        return
    for arg in get_args(tp):
        _configure(arg, seen)


_ADAPTERS: dict[Any, TypeAdapter[Any]] = {}


def _adapter(cls: type[T]) -> TypeAdapter[T]:
    """The pydantic validator of dataclass ``cls`` (and every dataclass in it), made once."""
    if cls not in _ADAPTERS:
        _configure(cls, set())
        _ADAPTERS[cls] = TypeAdapter(cls)
    return _ADAPTERS[cls]


def _jsonable(value: Any) -> Any:
    """``value`` as JSON can carry it (paths as text, non-finite floats kept for the validator to refuse)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def _field_type(cls: Any, loc: Sequence[Any]) -> Any:
    """The annotation found by following ``loc`` (field names, indexes) from dataclass ``cls`` (``None``: lost)."""
    tp = cls
    for key in loc:
        while get_origin(tp) in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            tp = next((a for a in args if dataclasses.is_dataclass(a)), args[0] if args else None)
        if dataclasses.is_dataclass(tp) and isinstance(key, str):
            tp = get_type_hints(tp).get(key)
        elif get_origin(tp) in (list, tuple, dict):
            params = get_args(tp)
            tp = params[-1] if get_origin(tp) is dict or (len(params) == 2 and params[1] is Ellipsis) \
                or len(params) == 1 else params[key] if isinstance(key, int) and key < len(params) else None
        elif not (isinstance(key, str) and get_origin(tp) in (Union, types.UnionType)):
            return None
    return tp


_EXPECTED = {"float": "a number", "int": "an integer", "bool": "true or false", "string": "a string",
             "dict": "a mapping", "list": "a list", "tuple": "a list", "dataclass": "a mapping", "path": "a file path",
             "model": "a mapping"}


def _message(cls: Any, err: Mapping[str, Any], path: str) -> str:
    """One pydantic error as the package words it: the key path, what was given and what is valid."""
    loc = [p for p in err.get("loc", ()) if not (isinstance(p, str) and (p.startswith("function-") or "[" in p))]
    where = path
    for key in loc:
        where = f"{where}[{key}]" if isinstance(key, int) else f"{where}.{key}" if where else str(key)
    kind, value = str(err.get("type", "")), err.get("input")
    if kind in ("extra_forbidden", "unexpected_keyword_argument"):
        owner = _field_type(cls, loc[:-1])
        valid = sorted(f.name for f in dataclasses.fields(owner) if f.init) if dataclasses.is_dataclass(owner) else []
        return (f"unknown key '{where}'; valid keys here are: {', '.join(valid)}"
                + _did_you_mean(loc[-1], valid))
    if kind in ("missing", "missing_argument"):
        return f"missing required key '{where}'"
    where = where or "<root>"
    if kind == "literal_error":
        choices = list(get_args(_field_type(cls, loc)) or ())
        listed = ", ".join(repr(c) for c in choices) or str(err.get("ctx", {}).get("expected"))
        return f"{where}: got {value!r}; valid choices are {listed}" + _did_you_mean(value, [str(c) for c in choices])
    if kind == "finite_number":
        return f"{where}: expected a finite number, got {value!r}"
    if kind.endswith("_type") or kind.endswith("_parsing"):
        word = _EXPECTED.get(kind.rsplit("_", 1)[0].replace("_", ""), kind.rsplit("_", 1)[0])
        return f"{where}: expected {word}, got {value!r}"
    if kind == "too_short" or kind == "too_long":
        return f"{where}: expected a list of {len(get_args(_field_type(cls, loc)))} items, got {len(value or ())}"
    return f"{where}: {err.get('msg', 'invalid')}, got {value!r}"


def _strip_removed(tp: Any, data: Any, path: str) -> Any:
    """``data`` without the keys a dataclass on its way lists in ``REMOVED_KEYS``, at every level.

    ``REMOVED_KEYS``: key → why it is read and ignored; one ``FutureWarning`` each.
    """
    while get_origin(tp) in (Union, types.UnionType):
        tp = next((a for a in get_args(tp) if dataclasses.is_dataclass(a)), None)
    if not (dataclasses.is_dataclass(tp) and isinstance(data, dict)):
        return data
    removed: dict[str, str] = getattr(tp, "REMOVED_KEYS", {})
    out = {}
    hints = get_type_hints(tp)
    for key, value in data.items():
        where = f"{path}.{key}" if path else str(key)
        if key in removed:
            warnings.warn(f"'{where}' is ignored: {removed[key]}; remove it from the file", FutureWarning,
                          stacklevel=4)
            continue
        out[key] = _strip_removed(hints[key], value, where) if key in hints else value
    return out


def from_dict(cls: type[T], data: dict[str, Any] | None, path: str = "") -> T:
    """Build dataclass ``cls`` from a plain mapping, validating every key and value.

    pydantic, strict (see :data:`_STRICT`); each dataclass's ``__post_init__`` checks its ranges.

    Args:
        cls: the dataclass type.
        data: mapping from YAML or a file aerialmtl wrote (``None`` means all defaults).
        path: key path of ``data`` inside the whole document, used in messages.

    Raises:
        ConfigError: unknown key, missing required key, wrong type or bad choice; the message names
            the key path and the valid keys/choices. A ``__post_init__``'s own error (an
            :class:`~aerialmtl.errors.AerialMTLError`) passes through as it was raised.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{path or '<root>'}: expected a mapping, got {data!r}")
    data = _strip_removed(cls, data, path)
    try:
        return _adapter(cls).validate_json(json.dumps(_jsonable(data), allow_nan=True))
    except ValidationError as exc:
        errors = exc.errors()
        # a typo is both an unknown key and a missing one: name the typo first (with its "did you mean")
        first = next((e for e in errors if e.get("type") in ("extra_forbidden", "unexpected_keyword_argument")),
                     errors[0])
        inner = (first.get("ctx") or {}).get("error")
        if isinstance(inner, AerialMTLError):  # raised by a __post_init__: already worded
            raise inner from None
        if isinstance(inner, (ValueError, TypeError)):
            raise ConfigError(f"{path or cls.__name__}: {inner}") from exc
        raise ConfigError(_message(cls, first, path)) from exc
    except TypeError as exc:
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
    """PyYAML's safe loader reading floats as YAML 1.2 does: ``1e-4`` and ``1e3`` are numbers.

    YAML 1.1, which PyYAML follows, wants a dot and a signed exponent, so ``lr: 1e-4`` would be the string ``'1e-4'``).
    """


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"""),
    list("-+0123456789"),
)


#: Values (scalars, lists and mappings) a YAML file may hold once its aliases are expanded: a configuration has a
#: few hundred, a tile folder's ``dataset.yaml`` a few thousand. Aliases of aliases (``&a [*b, *b, ...]``, the
#: "billion laughs") stay small as a file and as PyYAML's graph, but every walk of the tree (validation, a
#: copy, a comparison) would visit 10⁹ values: such a file is refused before it is built.
MAX_YAML_VALUES = 1_000_000


def _expanded_values(node: yaml.Node, sizes: dict[int, int], open_: set[int]) -> int:
    """The values under ``node`` once every alias is expanded (:data:`MAX_YAML_VALUES` + 1 stands for "more";
    a node that contains itself counts as more).
    """
    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in open_:
        return MAX_YAML_VALUES + 1
    total = 1
    if isinstance(node, (yaml.SequenceNode, yaml.MappingNode)):
        open_.add(key)
        children = node.value if isinstance(node, yaml.SequenceNode) else [n for pair in node.value for n in pair]
        for child in children:
            total += _expanded_values(child, sizes, open_)
            if total > MAX_YAML_VALUES:
                total = MAX_YAML_VALUES + 1
                break
        open_.discard(key)
    sizes[key] = total
    return total


def read_yaml(path: str | Path) -> Any:
    """Parse a YAML file with a message naming the file on failure.

    Raises:
        ConfigError: missing, not YAML, nested too deeply, or more than :data:`MAX_YAML_VALUES` values once its
            aliases are expanded (refused before the tree is built).
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file '{p}' does not exist; pass the path of a YAML file")
    try:
        with p.open("r", encoding="utf-8") as fh:
            loader = _Loader(fh)
            try:
                node = loader.get_single_node()
                if node is None:
                    return None
                if _expanded_values(node, {}, set()) > MAX_YAML_VALUES:
                    raise ConfigError(
                        f"config file '{p}' expands to more than {MAX_YAML_VALUES:,} values through its YAML aliases "
                        "(*name): refused before reading it (an alias bomb, or a file that refers to itself); write "
                        "the values out, with fewer aliases")
                return loader.construct_document(node)
            finally:
                loader.dispose()
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file '{p}' is not valid YAML: {exc}") from exc
    except RecursionError:
        raise ConfigError(f"config file '{p}' nests lists or mappings too deeply to be a configuration; write it "
                          "flatter") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file '{p}' is not UTF-8 text ({exc.reason} at byte {exc.start}); save it as "
                          "UTF-8") from None


def load_yaml_config(path: str | Path, cls: type[T]) -> T:
    """Read YAML file ``path`` into dataclass ``cls`` (see :func:`from_dict`); errors name the file."""
    data = read_yaml(path)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


__all__ = ["MAX_YAML_VALUES", "from_dict", "load_yaml_config", "read_yaml", "to_dict"]
