"""`aerialmtl evaluate` (placeholder until the command lands)."""

import click


@click.command(name="evaluate")
def evaluate() -> None:
    """Not available yet."""
    raise click.UsageError("'aerialmtl evaluate' is not implemented yet")
