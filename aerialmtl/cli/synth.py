"""`aerialmtl synth` (placeholder until the command lands)."""

import click


@click.command(name="synth")
def synth() -> None:
    """Not available yet."""
    raise click.UsageError("'aerialmtl synth' is not implemented yet")
