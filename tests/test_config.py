"""YAML → dataclass loading: errors name the key path and the valid keys/choices."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from aerialmtl.config import from_dict, load_yaml_config, to_dict
from aerialmtl.errors import ConfigError


@dataclass(frozen=True)
class Optim:
    lr: float = 2e-4
    kind: Literal["adam", "sgd"] = "adam"
    betas: tuple[float, float] = (0.5, 0.999)


@dataclass(frozen=True)
class Root:
    name: str
    optim: Optim = field(default_factory=Optim)
    steps: int | None = None


def test_defaults_and_nested_values() -> None:
    cfg = from_dict(Root, {"name": "x", "optim": {"lr": 1, "betas": [0.9, 0.99]}})
    assert cfg.optim.lr == 1.0 and isinstance(cfg.optim.lr, float)
    assert cfg.optim.betas == (0.9, 0.99)
    assert from_dict(Root, to_dict(cfg)) == cfg


@pytest.mark.parametrize(
    "data, expected",
    [
        ({"name": "x", "optim": {"lr": 1e-3, "lrr": 2}}, "optim.lrr"),
        ({"name": "x", "optim": {"kind": "adamw"}}, "optim.kind"),
        ({"name": "x", "optim": {"lr": "fast"}}, "optim.lr"),
        ({"name": "x", "steps": 1.5}, "steps"),
        ({"optim": {}}, "name"),
    ],
)
def test_errors_name_the_key_path(data: dict, expected: str) -> None:
    with pytest.raises(ConfigError, match=expected.replace(".", r"\.")):
        from_dict(Root, data)


def test_unknown_key_lists_valid_keys_and_enum_lists_choices(tmp_path) -> None:
    with pytest.raises(ConfigError, match="valid keys here are: betas, kind, lr"):
        from_dict(Root, {"name": "x", "optim": {"learning_rate": 1}})
    p = tmp_path / "c.yaml"
    p.write_text("name: x\noptim:\n  kind: adamw\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: optim\.kind: got 'adamw'; valid choices are 'adam', 'sgd'"):
        load_yaml_config(p, Root)


def test_yaml_exponents_without_a_dot_are_numbers(tmp_path) -> None:
    """`lr: 1e-4` is a number in YAML 1.2 (PyYAML's YAML 1.1 would read the string '1e-4')."""
    p = tmp_path / "c.yaml"
    p.write_text("name: x\noptim:\n  lr: 1e-4\n  betas: [5e-1, 1E0]\n")
    cfg = load_yaml_config(p, Root)
    assert cfg.optim.lr == pytest.approx(1e-4) and cfg.optim.betas == (0.5, 1.0)
    p.write_text("name: 1e3x\noptim:\n  lr: '1e-4'\n")  # quoted stays a string, and is refused as one
    with pytest.raises(ConfigError, match=r"optim\.lr: expected a number, got '1e-4'"):
        load_yaml_config(p, Root)
