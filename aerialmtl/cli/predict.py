"""`aerialmtl predict` (placeholder until the command lands)."""

import click


@click.command(name="predict")
def predict() -> None:
    """Not available yet."""
    raise click.UsageError("'aerialmtl predict' is not implemented yet")
