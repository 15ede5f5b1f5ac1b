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


def _git(*args: str) -> list[str] | None:
    """``git -C ROOT args`` as lines, or None where this is no git checkout (an sdist, an installed copy)."""
    import shutil
    import subprocess

    if shutil.which("git") is None or not (ROOT / ".git").exists():
        return None
    run = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=False)
    return run.stdout.splitlines() if run.returncode == 0 else None


def _start_cards() -> list[Path]:
    from aerialmtl.formats import starts

    return sorted(p for p in starts.STARTS_DIR.glob(f"*{starts.CARD_SUFFIX}") if p.name != "README.md")


def test_every_start_card_has_its_weights_and_they_match_the_card() -> None:
    """A start the docs call shipped loads on a fresh clone: each card's weights file is there, of the card's size
    and SHA-256 (a card without its file made `train --init NAME` answer 'none in this installation')."""
    from aerialmtl.formats import starts
    from aerialmtl.formats.checkpoint import file_sha256

    cards = _start_cards()
    assert cards, "the package ships at least one start (the docs name synthcity-lite0)"
    for card_file in cards:
        card = starts.read_card(card_file)
        assert card.get("format") == starts.CARD_FORMAT, card_file
        weights = card_file.with_name(card["file"])
        assert weights.is_file(), f"{card_file.name} names {weights.name}, which is missing"
        assert weights.stat().st_size == card["size_bytes"], weights
        assert file_sha256(weights) == card["sha256"], f"{weights.name} is not the file its card describes"
        assert starts.resolve_start(card["name"]) == weights


def test_a_fresh_clone_holds_every_file_the_package_and_the_docs_name() -> None:
    """What the package's resources and the docs name is committed, not only present where it was made: no file
    under aerialmtl/resources is ignored by git (``*.pt`` was, so the shipped start never reached a clone), and
    every relative link of README.md and docs/ points at a tracked file."""
    import re

    tracked = _git("ls-files")
    if tracked is None:
        pytest.skip("not a git checkout: nothing to compare a fresh clone with")
    ignored = _git("ls-files", "--others", "--ignored", "--exclude-standard", "aerialmtl/resources") or []
    ignored = [p for p in ignored if "__pycache__" not in p]
    assert ignored == [], f"package resources git ignores (a fresh clone lacks them): {ignored}"
    tracked_set = set(tracked)
    tracked_dirs = {str(Path(p).parent) for p in tracked} | {str(q) for p in tracked for q in Path(p).parents}
    missing = []
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), ROOT / "samples" / "README.md"]
    for page in pages:
        for target in re.findall(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            if "://" in target or target.startswith(("mailto:", "/")):
                continue
            rel = (page.parent / target).resolve()
            try:
                name = str(rel.relative_to(ROOT))
            except ValueError:
                continue  # a link out of the repository (the site's own pages)
            if name.startswith("docs/images/built/"):
                continue  # drawn by the site build (docs_hooks.py) from a run, never committed
            if name not in tracked_set and name not in tracked_dirs:
                missing.append(f"{page.relative_to(ROOT)} → {target}")
    assert missing == [], "links to files a fresh clone lacks:\n" + "\n".join(missing)
