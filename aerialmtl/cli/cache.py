"""`aerialmtl cache`: see and clear what the package keeps between runs; a thin command over
:func:`aerialmtl.stores.list_stores` and :func:`aerialmtl.stores.clear_stores`.
"""

from __future__ import annotations

import click

from aerialmtl.cli.options import option
from aerialmtl.stores import DEFAULT_LIMIT_MB, LIMIT_ENV, ROOT_ENV, STORES, clear_stores, list_stores, size_limit


@click.command(name="cache")
@click.argument("action", type=click.Choice(["list", "clear"]), default="list", required=False)
@option("--store", "names", type=click.Choice(STORES), multiple=True,
        help="The store to list or clear (repeatable) [default: every store].")
def cache(action: str, names: tuple[str, ...]) -> None:
    """List (default) or clear the stores aerialmtl keeps between runs.

    \b
    openvino  converted and compiled OpenVINO models (AERIALMTL_OPENVINO_CACHE moves it)
    numba     the compiled kernels (MC class statistics, shadow step)
    Everything is rebuilt when needed: clearing only makes the next run slower. The stores live in the
    platform's cache folder (AERIALMTL_CACHE moves them) and hold at most AERIALMTL_CACHE_LIMIT_MB MiB
    together (least recently used entries go first). Only files aerialmtl wrote are counted or removed:
    a folder of yours that a store is pointed at keeps its files.
    """
    chosen = names or STORES
    if action == "clear":
        files, size, left = clear_stores(chosen)
        kept = f"; left {left} other file(s) there, which aerialmtl did not write" if left else ""
        click.echo(f"removed {files} file(s), {size / 2**20:.1f} MiB, from the {', '.join(chosen)} store(s){kept}")
        return
    try:
        limit = f"{size_limit() / 2**20:.0f} MiB"
    except ValueError as exc:
        limit = f"{DEFAULT_LIMIT_MB} MiB ({exc})"
    total = 0
    for name, folder, files, size, other in list_stores():
        if name in chosen:
            total += size
            extra = f" (and {other} other file(s), not aerialmtl's: never counted or removed)" if other else ""
            click.echo(f"{name:<9} {files:>5} file(s) {size / 2**20:>9.1f} MiB  {folder}{extra}")
    click.echo(f"total {total / 2**20:.1f} MiB of at most {limit} ({LIMIT_ENV}; move the stores with {ROOT_ENV})")
