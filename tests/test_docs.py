"""The documentation site covers the package: every page in the navigation, every public name in the API
reference, every command and option in the generated CLI reference with click's real defaults; the built site
shows no warning block, traceback, ``Sentinel`` or path of the machine that built it."""

from __future__ import annotations

import html
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import click
import numpy as np
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


def test_links_to_the_lab_notebook_lead_to_the_benchmarks_page_on_the_site() -> None:
    """Pages may link the lab notebook's files (``bench/RESULTS.md``, ``bench/results/*.md``: they work on GitHub
    and in a clone); the site does not render them, so its build points those links at the Benchmarks page's
    section that says where they are."""
    hooks = _docs_hooks()
    links = hooks.site_links  # type: ignore[attr-defined]
    md = "[b](../../bench/RESULTS.md#real-data) and [c](../bench/RESULTS.md)"
    assert links(md, "tutorials/small-area.md") == ("[b](../benchmarks.md#the-lab-notebook) and "
                                                     "[c](../benchmarks.md#the-lab-notebook)")
    assert links("[c](../bench/RESULTS.md)", "index.md") == "[c](benchmarks.md#the-lab-notebook)"
    assert links("[u](../../bench/results/uncertainty.md#x)", "tutorials/a.md") == \
        "[u](../benchmarks.md#the-lab-notebook)"
    assert "## The lab notebook" in (DOCS / "benchmarks.md").read_text()
    for page in ("tutorials/small-area.md", "getting-started.md", "index.md"):
        text = (DOCS / page).read_text()
        for link, anchor in re.findall(r"\]\(((?:\.\./)+bench/(?:RESULTS|results/\w+)\.md)(#[^)]*)?\)", text):
            target = ((DOCS / page).parent / link).resolve()
            assert target.is_file(), (page, link)
            if anchor:  # the heading it names is there (GitHub's and the site's anchors agree for these)
                slugs = {re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", h.replace("`", "")).strip().lower())
                         for h in re.findall(r"^#+ (.+)$", target.read_text(), flags=re.M)}
                assert anchor[1:] in slugs, (page, link, anchor)


# ---- what the pages say ----------------------------------------------------------------------------
#: A mention of the project's issue tracker ("issue 48", "issues 46, 47", "Issue #12"): the history of how a
#: result was found, which belongs in the lab notebook (bench/results, experiments/), not on a user's page.
ISSUE_MENTION = re.compile(r"\bissues?\s*#?\d+", flags=re.I)
#: A line that includes another file into a page (pymdownx.snippets): the page shows that file's words.
SNIPPET = re.compile(r'^--8<--\s+"([^"]+)"\s*$', flags=re.M)


def _page_source(path: Path) -> str:
    """What a page of the site shows, as text: a Markdown page with its included files (snippets) expanded,
    a notebook's Markdown and code cells."""
    if path.suffix == ".ipynb":
        cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
        return "\n".join("".join(c["source"]) for c in cells)
    text = path.read_text(encoding="utf-8")
    return SNIPPET.sub(lambda m: (REPO / m.group(1)).read_text(encoding="utf-8"), text)


def _site_pages() -> list[Path]:
    """Every page of the site's navigation (the notebook through its link in docs/)."""
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text())
    return [(DOCS / page).resolve() for page in _nav_pages(config["nav"])]


def test_the_pages_tell_results_not_the_history_of_how_they_were_found() -> None:
    """No page mentions an issue of the project's tracker, and none shows a path of a machine that built or
    measured something (the checkout, Python's prefix, the home folder, a folder the build made in /tmp)."""
    hooks = _docs_hooks()
    paths = hooks.machine_paths()  # type: ignore[attr-defined]
    temporary = re.compile(re.escape(tempfile.gettempdir().rstrip(os.sep) + os.sep) + hooks.TEMP_NAMES)  # type: ignore[attr-defined]
    found = []
    for page in [*_site_pages(), REPO / "README.md"]:
        text = _page_source(page)
        found += [(page.name, m.group(0)) for m in ISSUE_MENTION.finditer(text)]
        found += [(page.name, p) for p in paths if p in text]
        found += [(page.name, m.group(0)) for m in temporary.finditer(text)]
    assert not found, found


def test_the_benchmarks_page_is_what_a_user_needs_not_the_lab_notebook() -> None:
    """The Benchmarks page (with whatever it includes) stays under 5,000 words; the lab notebook it once
    rendered (over 50,000) stays in the repository."""
    words = len(_page_source(DOCS / "benchmarks.md").split())
    assert words <= 5000, f"docs/benchmarks.md shows {words} words"


#: Width in CSS pixels of the site's text column in a 1280-px-wide browser window (the Material theme with both
#: sidebars); a figure wider than it is scaled down to fit.
COLUMN_PX = 690


@pytest.mark.parametrize("figure", ["products_figure", "styled_figure"])
def test_the_site_figures_text_reads_at_least_11_px_in_the_text_column(figure: str, tmp_path: Path) -> None:
    """The maps the build draws (docs_hooks.py) show no text under 11 px once fitted to the text column at 1280 px
    (their titles, colour-bar labels, ticks and legends)."""
    pytest.importorskip("matplotlib")
    from helpers.rasters import write_prediction_folder
    from matplotlib.text import Text

    hooks = _docs_hooks()
    from aerialmtl.formats.qgis_style import VIRIDIS, pseudocolor_style, write_style

    pred = write_prediction_folder(tmp_path / "pred", np.random.default_rng(0))
    for name in ("height", "height_std"):  # the styles predict writes beside its layers
        write_style(pred / f"{name}.qml", pseudocolor_style(0.0, 20.0, VIRIDIS, -9999.0, "m"))
    draw = getattr(hooks, figure)
    fig = draw(pred, tmp_path / "ortho.tif", "a title") if figure == "products_figure" else draw(pred, "a title")
    sizes = [t.get_fontsize() for t in fig.findobj(Text) if t.get_text().strip() and t.get_visible()]
    png = tmp_path / "figure.png"
    png.write_bytes(hooks._png(fig, hooks.DPI))  # type: ignore[attr-defined]
    from PIL import Image

    with Image.open(png) as im:
        width = im.width
    scale = min(1.0, COLUMN_PX / width)
    assert sizes and min(sizes) * hooks.DPI / 72 * scale >= 11, (min(sizes), width)  # type: ignore[attr-defined]


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
