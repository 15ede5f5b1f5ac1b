"""Run ``aerialmtl`` under torchrun and record which files this process changes inside a folder.

Usage (by tests/test_distributed.py): ``torchrun ... tests/torchrun_audit.py WATCHED RECORD_DIR train ...``.
A Python audit hook notes every file opened for writing, renamed, removed or created under WATCHED; at exit
the list goes to ``RECORD_DIR/writes-rank<RANK>.txt`` (outside WATCHED). torch.save writes through C++,
but its atomic rename into place is seen.
"""

from __future__ import annotations

import atexit
import os
import sys
from pathlib import Path

watched = str(Path(sys.argv[1]).resolve())
record = Path(sys.argv[2])
events: list[str] = []


def _inside(path: object) -> bool:
    if isinstance(path, (str, bytes, os.PathLike)):
        p = os.fsdecode(path)
        return os.path.abspath(p).startswith(watched)
    return False


def _hook(event: str, args: tuple) -> None:
    if event == "open" and len(args) >= 2 and _inside(args[0]):
        mode = args[1] if isinstance(args[1], str) else ""
        flags = args[2] if len(args) > 2 and isinstance(args[2], int) else 0
        if any(c in mode for c in "wax+") or flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            events.append(f"open {args[0]}")
    elif event in ("os.rename", "os.replace", "os.remove", "os.unlink", "os.mkdir", "shutil.rmtree") and args \
            and any(_inside(a) for a in args[:2]):
        events.append(f"{event} {args[0]}")


@atexit.register
def _dump() -> None:
    record.mkdir(parents=True, exist_ok=True)
    (record / f"writes-rank{os.environ.get('RANK', '0')}.txt").write_text("\n".join(events))


sys.addaudithook(_hook)
from aerialmtl.cli import main  # noqa: E402

main(sys.argv[3:])
