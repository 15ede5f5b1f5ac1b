"""`aerialmtl tile` (placeholder until the command lands)."""

import click


@click.command(name="tile")
def tile() -> None:
    """Not available yet."""
    raise click.UsageError("'aerialmtl tile' is not implemented yet")
