"""``aerialmtl`` on the command line: the console script and ``python -m aerialmtl``.

The command line itself imports only click and aerialmtl's light modules (``--help`` answers at once); each
command imports its library (torch, OpenVINO, GDAL) when it runs, with Python's cyclic garbage collector
paused and what the imports made frozen out of its sight (:func:`aerialmtl.cli._prepared`).
"""

from __future__ import annotations

from aerialmtl.cli import main as cli_main


def main() -> None:
    """Run the ``aerialmtl`` command line (:func:`aerialmtl.cli.main`)."""
    cli_main()


if __name__ == "__main__":
    main()
