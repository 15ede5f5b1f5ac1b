"""``aerialmtl`` on the command line: the console script and ``python -m aerialmtl``.

:func:`main` imports the commands (torch, OpenVINO, GDAL: about a million Python objects) with Python's cyclic
garbage collector paused, then moves everything they made out of its sight (:func:`gc.freeze`): those objects
live as long as the process, and walking them again in every full collection during a run and once more at
exit cost ~0.5 s of a 2.2 s warm ``predict`` (bench/RESULTS.md, issue 27). Objects made by the command itself
are collected as usual.
"""

from __future__ import annotations

import gc


def main() -> None:
    """Run the ``aerialmtl`` command line (:func:`aerialmtl.cli.main`)."""
    gc.disable()
    try:
        from aerialmtl.cli import main as cli_main
    finally:
        gc.freeze()
        gc.enable()
    cli_main()


if __name__ == "__main__":
    main()
