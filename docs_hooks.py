"""MkDocs hooks of the documentation site (``hooks:`` in mkdocs.yml): what the site must never show.

* The command-line reference (mkdocs-click) prints ``option.default``; click 8.3+ keeps ``UNSET`` there for
  an option declared without a default, which the table showed as ``Sentinel.UNSET``.
  :func:`use_real_defaults` makes the table show what click itself uses (``False`` for a flag, ``None`` for
  an option that is simply not passed). tests/test_docs.py renders the page through the same function.
* A page that shows a warning, a traceback, ``Sentinel`` or a path of the machine that built the site fails
  the build (:func:`problems`): the notebook pages are run at build time, and a cell that prints a warning
  (a stderr output block) or the build's temporary folder would otherwise be published as it is.
"""

from __future__ import annotations

import copy
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent


# ---- the CLI reference's defaults ---------------------------------------------------------------
def real_default(option: Any) -> Any:
    """The default click uses for ``option`` (``None`` for an option without one, ``False`` for a flag)."""
    import click

    default = option.default
    if default is None or not _is_unset(default):
        return default
    if getattr(option, "is_flag", False) and not getattr(option, "multiple", False):
        value = option.get_default(click.Context(click.Command("docs")), call=False)
        return None if _is_unset(value) else value
    return None


def _is_unset(value: Any) -> bool:
    """Whether ``value`` is click's marker for "no default given" (click 8.3+)."""
    return type(value).__name__ == "Sentinel" or repr(value).startswith("Sentinel.")


def use_real_defaults() -> None:
    """Make mkdocs-click's option tables show :func:`real_default` (idempotent)."""
    from mkdocs_click import _docs

    original = _docs._format_table_option_row
    if getattr(original, "real_defaults", False):
        return

    def row(option: Any) -> str:
        shown = copy.copy(option)
        shown.default = real_default(option)
        return str(original(shown))

    row.real_defaults = True  # type: ignore[attr-defined]
    _docs._format_table_option_row = row


# ---- what no page may show ---------------------------------------------------------------------
#: A notebook cell's stderr output (a warning, a progress bar) as nbconvert renders it.
STDERR_BLOCK = re.compile(r'<[^>]*(data-mime-type="application/vnd\.jupyter\.stderr"|class="[^"]*output_stderr)')
#: Names of folders made by :mod:`tempfile` (``tmpab12cd34``), pytest and the uncertainty notebook.
TEMP_NAMES = r"(?:tmp[a-z0-9_]{8}|pytest-of-|aerialmtl_nb_)"


def machine_paths() -> list[str]:
    """Absolute paths of this machine that a page must not show: the checkout, Python's prefix and the home
    folder, each with a trailing separator.
    """
    paths = {str(REPO), sys.prefix, sys.base_prefix, os.path.expanduser("~")}
    return sorted({p.rstrip(os.sep) + os.sep for p in paths if len(p.strip(os.sep)) > 0})


def temporary_paths(html: str) -> list[str]:
    """Folders the build made in the temporary folder that ``html`` shows (``/tmp/aerialmtl_nb_x1y2``); a
    command in prose (``aerialmtl demo /tmp/demo3``) is not one.
    """
    tmp = re.escape(tempfile.gettempdir().rstrip(os.sep) + os.sep)
    return sorted(set(re.findall(tmp + TEMP_NAMES + r"[\w.-]*", html)))


def problems(html: str) -> list[str]:
    """What is wrong with a built page's HTML: warning blocks, tracebacks, ``Sentinel``, this machine's paths."""
    found = []
    if STDERR_BLOCK.search(html):
        found.append("a cell's stderr output (a warning or a progress bar)")
    for word in ("Traceback", "Sentinel"):
        if word in html:
            found.append(f"'{word}'")
    for path in machine_paths() + temporary_paths(html):
        if path in html:
            found.append(f"the path {path} of the machine that built the site")
    return found


# ---- the hooks ------------------------------------------------------------------------------------
def on_startup(**kwargs: Any) -> None:
    """Before the pages are read: the CLI reference's defaults."""
    use_real_defaults()


def on_page_content(html: str, page: Any, **kwargs: Any) -> str:
    """Fail the build on a page with :func:`problems`."""
    found = problems(html)
    if found:
        from mkdocs.exceptions import PluginError

        raise PluginError(f"{page.file.src_uri} shows {'; '.join(found)}: fix the page (a notebook cell that "
                          "prints a warning: silence it or fix its cause in the notebook)")
    return html
