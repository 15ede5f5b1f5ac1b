"""The documentation site covers the package: every page in the navigation, every public name in the API
reference, every command and option in the generated CLI reference (the strict build itself runs in .ci/run)."""

from __future__ import annotations

import html
import re
from pathlib import Path

import click
import pytest
import yaml

import aerialmtl
from aerialmtl.cli import cli

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"


def _nav_pages(nav: object) -> list[str]:
    if isinstance(nav, str):
        return [nav]
    if isinstance(nav, list):
        return [p for item in nav for p in _nav_pages(item)]
    if isinstance(nav, dict):
        return [p for value in nav.values() for p in _nav_pages(value)]
    return []


def test_every_page_is_in_the_navigation_and_exists() -> None:
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text())
    pages = _nav_pages(config["nav"])
    assert len(pages) == len(set(pages))
    assert sorted(pages) == sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*")
                                   if p.suffix in (".md", ".ipynb"))
    for page in pages:
        assert (DOCS / page).resolve().is_file(), page


def test_the_api_reference_documents_every_public_name() -> None:
    text = (DOCS / "reference" / "api.md").read_text()
    documented = set(re.findall(r"^::: (aerialmtl[\w.]*)$", text, flags=re.M))
    for name in aerialmtl.__all__:
        if name == "__version__":
            continue
        module = aerialmtl._EXPORTS[name]
        assert f"{module}.{name}" in documented or (module.endswith(f".{name}") and module in documented), name


def test_the_cli_reference_shows_every_command_and_option() -> None:
    """Render the page as the site does (mkdocs-click) and look for every command and option in it."""
    markdown = pytest.importorskip("markdown")
    pytest.importorskip("mkdocs_click")
    page = markdown.markdown((DOCS / "reference" / "cli.md").read_text(), extensions=["mkdocs-click", "tables"])
    text = html.unescape(re.sub("<[^>]+>", " ", page))
    for name, command in cli.commands.items():
        assert f"aerialmtl {name}" in text, name
        for p in command.params:
            for opt in p.opts if isinstance(p, click.Option) else ():
                assert re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", text), (name, opt)
    for p in cli.params:
        for opt in p.opts:
            assert opt in text, opt


def test_the_readme_keeps_the_two_commands_and_its_links() -> None:
    """A newcomer's two commands stay in the README (the test one is what CI runs), and its links resolve."""
    readme = (REPO / "README.md").read_text()
    demo = 'pip install torch==2.13.0 -e ".[plot]" && aerialmtl demo demo_out'
    tests = 'pip install torch==2.13.0 -e ".[test]" && python -m pytest -q'
    assert f"```bash\n{demo}\n```" in readme and f"```bash\n{tests}\n```" in readme
    assert tests in (REPO / ".ci" / "run").read_text()
    assert f"```bash\n{demo}\n```" in (DOCS / "getting-started.md").read_text()
    for link in re.findall(r"\]\(([^)#]+)\)", readme):
        if not link.startswith(("http://", "https://")):
            assert (REPO / link).exists(), link
