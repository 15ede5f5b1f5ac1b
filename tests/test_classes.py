"""Class schemes: shipped schemes load, codes remap to contiguous indices, unknown codes are reported."""

from __future__ import annotations

import numpy as np
import pytest

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import ConfigError, LabelError


@pytest.mark.parametrize("name, k", [("dfc2018", 20), ("isprs", 6), ("synthetic", 6)])
def test_builtin_schemes(name: str, k: int) -> None:
    scheme = ClassScheme.load(name)
    assert scheme.num_classes == k
    assert len(set(scheme.names)) == k
    assert ClassScheme.from_dict(scheme.to_dict()) == scheme


def test_remap_codes_ignore_and_nodata() -> None:
    scheme = ClassScheme.load("dfc2018")
    codes = np.array([[0, 1, 20], [8, 7, 3]], dtype=np.uint8)
    valid = np.array([[True, True, True], [True, False, True]])
    out = scheme.remap(codes, valid)
    assert out.dtype == np.uint8
    assert out.tolist() == [[IGNORE_INDEX, 0, 19], [7, IGNORE_INDEX, 2]]


def test_unknown_codes_error_lists_them_or_are_ignored_on_request() -> None:
    scheme = ClassScheme.load("synthetic")
    codes = np.array([1, 9, 42, 0, 2])
    with pytest.raises(LabelError, match=r"codes 9, 42 are not in class scheme 'synthetic'"):
        scheme.remap(codes, source="lab.tif")
    assert scheme.remap(codes, on_unknown="ignore").tolist() == [0, IGNORE_INDEX, IGNORE_INDEX, IGNORE_INDEX, 1]


def test_bad_scheme_names_the_problem(tmp_path) -> None:
    p = tmp_path / "s.yaml"
    p.write_text("name: s\nclasses:\n  - {code: 1, name: a}\n  - {code: 1, name: b}\n")
    with pytest.raises(ConfigError, match=r"codes \[1\] are listed more than once"):
        ClassScheme.load(p)
    with pytest.raises(ConfigError, match="not found"):
        ClassScheme.load(tmp_path / "missing.yaml")
