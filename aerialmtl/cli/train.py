"""`aerialmtl train` (placeholder until the command lands)."""

import click


@click.command(name="train")
def train() -> None:
    """Not available yet."""
    raise click.UsageError("'aerialmtl train' is not implemented yet")
