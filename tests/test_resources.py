"""The configs and class schemes users see in configs/ are the ones the installed package ships."""

from __future__ import annotations

from pathlib import Path

import pytest

from aerialmtl.demo import builtin_config

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "aerialmtl" / "resources"


@pytest.mark.parametrize("sub", ["classes", "configs"])
def test_packaged_copies_match_the_repository_configs(sub: str) -> None:
    repo = ROOT / "configs" / sub if sub == "classes" else ROOT / "configs"
    repo_files = {p.name: p.read_bytes() for p in repo.glob("*.yaml")}
    pkg_files = {p.name: p.read_bytes() for p in (PKG / sub).glob("*.yaml")}
    assert repo_files and repo_files == pkg_files, f"copy configs/ into aerialmtl/resources/{sub}/ (or back)"


def test_builtin_config_is_found_in_the_package_and_unknown_names_list_the_choices() -> None:
    assert builtin_config("d3net_small_synth") == PKG / "configs" / "d3net_small_synth.yaml"
    with pytest.raises(FileNotFoundError, match="d3net_dfc2018"):
        builtin_config("nope")
