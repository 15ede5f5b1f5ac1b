"""What a killed run or another process left at a store entry's staging name never stops the write (issue 60).

A store writes an entry as ``.NAME.partial.PID`` and renames it into place (:mod:`aerialmtl.filesafety`, the one
atomic write of the package). A symbolic link or a FIFO at that name is removed and the entry written anew:
the link's target is never written through, a FIFO never takes the entry's bytes, and the store stays on.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from aerialmtl import stores


@pytest.mark.parametrize("what", ["symlink", "fifo"])
def test_a_store_entry_is_written_past_a_link_or_fifo_at_its_staging_name(what: str, tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch,
                                                                          recwarn: pytest.WarningsRecorder) -> None:
    monkeypatch.setenv("AERIALMTL_CACHE", str(tmp_path / "cache"))
    store = stores.Store(tmp_path / "cache" / "numba", "cached kernel")
    staging = tmp_path / "cache" / "numba" / f".e.partial.{os.getpid()}"
    staging.parent.mkdir(parents=True)
    victim = tmp_path / "victim.txt"
    victim.write_bytes(b"a user's file")
    reader = None
    if what == "symlink":
        staging.symlink_to(victim)
    else:
        os.mkfifo(staging)
        reader = os.open(staging, os.O_RDONLY | os.O_NONBLOCK)  # a writer into it would not block: it would fill it
    try:
        stores.reset_warnings()
        store.write("e", [b"payload"])
    finally:
        if reader is not None:
            os.close(reader)
    assert store.read("e") == [b"payload"]
    assert victim.read_bytes() == b"a user's file"
    assert not os.path.lexists(staging)
    assert not [w for w in recwarn if issubclass(w.category, UserWarning)], [str(w.message) for w in recwarn]
