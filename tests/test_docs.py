"""The documentation site covers the package: every page in the navigation, every public name in the API
reference, every command and option in the generated CLI reference with click's real defaults; the built site
shows no warning block, traceback, ``Sentinel`` or path of the machine that built it."""

from __future__ import annotations

import html
import importlib.util
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import click
import pytest
import yaml

import aerialmtl
from aerialmtl.cli import cli

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"


def _docs_hooks() -> object:
    """The site's hooks module (docs_hooks.py, beside mkdocs.yml)."""
    spec = importlib.util.spec_from_file_location("docs_hooks", REPO / "docs_hooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    markdown = pytest.importorskip("markdown", reason="the test extra installs markdown and mkdocs-click")
    pytest.importorskip("mkdocs_click", reason="the test extra installs markdown and mkdocs-click")
    _docs_hooks().use_real_defaults()  # type: ignore[attr-defined]  # as the site's build does (mkdocs.yml hooks)
    page = markdown.markdown((DOCS / "reference" / "cli.md").read_text(), extensions=["mkdocs-click", "tables"])
    text = html.unescape(re.sub("<[^>]+>", " ", page))
    assert "Sentinel" not in text and "UNSET" not in text  # click 8.3+'s marker for "no default"
    rows = [re.findall(r"<td>(.*?)</td>", row, flags=re.S) for row in re.findall(r"<tr>.*?</tr>", page, flags=re.S)]
    defaults = {(cells[0], cells[3]) for cells in rows if len(cells) == 4}
    assert {d for name, d in defaults if name == "<code>--overwrite</code>"} == {"<code>False</code>"}  # a flag: off
    assert ("<code>--size</code>", "<code>320</code>") in defaults  # tile's patch side
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


def test_getting_started_states_the_time_its_sample_output_shows() -> None:
    """The page said "about 6 min" right above a sample output ending "Done in 3903 s": the prose must name the
    time the sample shows (and say why it differs from the quiet machine's)."""
    text = (DOCS / "getting-started.md").read_text()
    done = re.search(r"^Done in (\d+) s\.", text, flags=re.M)
    assert done, "the sample output's 'Done in N s' line"
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    seconds = int(done.group(1))
    assert f"{seconds} s" in prose and f"about {round(seconds / 60)} min" in prose, "state the sample's time"


def test_links_to_the_benchmarks_file_lead_to_the_benchmarks_page_on_the_site() -> None:
    """Pages link ``bench/RESULTS.md`` itself (it works on GitHub and in a clone; ``docs/benchmarks.md`` is an
    include line there); the site's build points those links at its Benchmarks page, anchors kept."""
    hooks = _docs_hooks()
    links = hooks.site_links  # type: ignore[attr-defined]
    md = "[b](../../bench/RESULTS.md#real-data) and [c](../bench/RESULTS.md)"
    assert links(md, "tutorials/small-area.md") == "[b](../benchmarks.md#real-data) and [c](../benchmarks.md)"
    assert links("[c](../bench/RESULTS.md)", "index.md") == "[c](benchmarks.md)"
    assert links("[u](../../bench/results/uncertainty.md#x)", "tutorials/a.md") == "[u](../benchmarks.md#x)"
    for page in ("tutorials/small-area.md", "getting-started.md", "index.md"):
        text = (DOCS / page).read_text()
        for link, anchor in re.findall(r"\]\(((?:\.\./)+bench/(?:RESULTS|results/\w+)\.md)(#[^)]*)?\)", text):
            target = ((DOCS / page).parent / link).resolve()
            assert target.is_file(), (page, link)
            if anchor:  # the heading it names is there (GitHub's and the site's anchors agree for these)
                slugs = {re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", h.replace("`", "")).strip().lower())
                         for h in re.findall(r"^#+ (.+)$", target.read_text(), flags=re.M)}
                assert anchor[1:] in slugs, (page, link, anchor)


# ---- the built site ----------------------------------------------------------------------------------
#: What no page of the site may show: a notebook cell's stderr block (a warning), a traceback, click's
#: marker for "no default", and paths of the machine that built it (checkout, Python, home, build temp folders).
_MACHINE = {str(REPO), sys.prefix, os.path.expanduser("~")}
_TMP = re.escape(tempfile.gettempdir().rstrip(os.sep) + os.sep)
FORBIDDEN = [re.compile(r'<[^>]*data-mime-type="application/vnd\.jupyter\.stderr"'), re.compile("Traceback"),
             re.compile("Sentinel"),
             *(re.compile(re.escape(p.rstrip(os.sep) + os.sep)) for p in _MACHINE if p.strip(os.sep)),
             re.compile(_TMP + r"(?:tmp[a-z0-9_]{8}|aerialmtl_nb_|aerialmtl_docs_)")]


@pytest.mark.slow
def test_the_built_site_shows_no_warning_traceback_sentinel_or_machine_path(tmp_path: Path) -> None:
    """Build the site as .ci/run does (~2 min: the notebook runs) and grep every page."""
    pytest.importorskip("mkdocs", reason="building the site needs the docs extra: pip install -e '.[docs]'")
    for plugin in ("material", "mkdocs_jupyter", "mkdocstrings", "mkdocs_click"):
        pytest.importorskip(plugin, reason="building the site needs the docs extra: pip install -e '.[docs]'")
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)], cwd=REPO,
                          capture_output=True, text=True, env=env, timeout=1200)
    assert done.returncode == 0, done.stderr[-3000:]
    pages = sorted(site.rglob("*.html"))
    assert len(pages) >= 15
    found = [(str(page.relative_to(site)), m.group(0)) for page in pages for pattern in FORBIDDEN
             if (m := pattern.search(page.read_text(encoding="utf-8")))]
    assert not found, found
    # the pages a newcomer meets first show what the package makes (figures the build drew, light enough)
    for name in ("index.html", "getting-started/index.html", "tutorials/small-area/index.html",
                 "tutorials/qgis/index.html"):
        images = re.findall(r'<img[^>]+src="([^"]*images/built/[^"]+\.png)"', (site / name).read_text())
        assert images, f"{name} shows no picture of the package's output"
        for src in images:
            png = ((site / name).parent / src).resolve()
            assert 5_000 < png.stat().st_size < 600_000, (name, src, png.stat().st_size)
    # the notebook page's outputs read as a page: no raw floats, no nan, no JSON dump (its code cells left out)
    notebook = (site / "tutorials" / "uncertainty_maps" / "index.html").read_text()
    outputs = re.sub(r'<div class="highlight[^"]*"><pre>.*?</pre>|<div class="clipboard-copy-txt"[^>]*>.*?</div>'
                     r"|<script.*?</script>", "", notebook, flags=re.S)  # code, its copy buttons, the theme's config
    shown = html.unescape(re.sub(r"<[^>]+>", " ", re.sub(r'src="data:[^"]*"', "", outputs)))
    assert not re.search(r"\d\.\d{12,}", shown), re.search(r".{40}\d\.\d{12,}.{20}", shown)
    assert not re.search(r"\bnan\b", shown, flags=re.I), re.search(r".{60}\bnan\b", shown, flags=re.I)
    assert not re.search(r'\{\s*"\w+":', shown), "a JSON dump"
