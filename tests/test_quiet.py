"""Warnings silenced in one thread stay silenced there only (aerialmtl.quiet): a run's later warnings (a cache that
cannot be written, a fallback) reach the user whatever its reader, stitch and writer threads did meanwhile."""

from __future__ import annotations

import ast
import threading
import warnings
from pathlib import Path

import aerialmtl
from aerialmtl.quiet import ignoring_warnings

PACKAGE = Path(aerialmtl.__file__).parent


class _OpeningWarning(UserWarning):
    """Stands for rasterio's NotGeoreferencedWarning, which a reader thread ignores while it opens its raster."""


def test_overlapping_blocks_of_two_threads_leave_the_process_filters_as_they_were() -> None:
    """The order that lost predict's warnings: the main thread starts a block ignoring UserWarning (reading the
    checkpoint), a reader thread starts one ignoring its opening warning, the main thread's ends, the reader's
    ends. With plain ``warnings.catch_warnings`` the reader's block saved the main thread's filters and put them
    back last, so UserWarning stayed ignored for the rest of the process; here the reader's block waits for the
    main thread's, and afterwards the filters are the process's own again."""
    with warnings.catch_warnings():  # this test's own filters, whatever happens below
        warnings.simplefilter("default")
        before = list(warnings.filters)
        main_in, reader_in, reader_done = threading.Event(), threading.Event(), threading.Event()
        seen_by_reader: list[list[tuple[object, ...]]] = []

        def reader() -> None:
            main_in.wait(5)
            with ignoring_warnings(_OpeningWarning):
                seen_by_reader.append(list(warnings.filters))
                reader_in.set()
            reader_done.set()

        thread = threading.Thread(target=reader)
        thread.start()
        with ignoring_warnings(UserWarning):
            main_in.set()
            reader_in.wait(0.5)  # with plain catch_warnings the reader is inside by now
        thread.join(10)
        assert reader_done.is_set()
        assert warnings.filters == before
        assert not any(f[0] == "ignore" and f[2] is UserWarning for f in seen_by_reader[0])  # its own filter only
        with warnings.catch_warnings(record=True) as shown:
            warnings.warn("the cache folder cannot be written", UserWarning, stacklevel=1)
        assert [str(w.message) for w in shown] == ["the cache folder cannot be written"]


def test_blocks_nest_in_one_thread_and_restore_on_error() -> None:
    """A block inside another in one thread does not wait for itself; an error inside leaves the filters as they
    were."""
    with warnings.catch_warnings():
        before = list(warnings.filters)
        try:
            with ignoring_warnings(UserWarning), ignoring_warnings():
                raise KeyError("inside")
        except KeyError:
            pass
        assert warnings.filters == before


#: Blocks that may use ``warnings`` filters directly: each encloses every thread it could meet.
ENCLOSING = {
    "quiet.py": "the lock's own block",
    "cli/__init__.py": "the command's block: entered before its threads start, left after they end",
    "training/sun_beside.py": "the sun process's recording block, around the whole fit in a process of its own",
}


def test_the_package_silences_warnings_only_through_the_lock() -> None:
    """Every ``catch_warnings``/``simplefilter``/``filterwarnings`` call of the package is in :data:`ENCLOSING`;
    a new one elsewhere could overlap another thread's block and lose the run's warnings again."""
    calls = {"catch_warnings", "simplefilter", "filterwarnings"}
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in calls \
                    and isinstance(node.func.value, ast.Name) and node.func.value.id == "warnings":
                found.append((rel, node.lineno))
    outside = [f"{rel}:{line}" for rel, line in found if rel not in ENCLOSING]
    assert not outside, f"use aerialmtl.quiet.ignoring_warnings instead at {outside}"
    assert {rel for rel, _ in found} == set(ENCLOSING)  # the list names no block that is gone
