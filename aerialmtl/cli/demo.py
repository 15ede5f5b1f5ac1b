"""`aerialmtl demo` (placeholder until the command lands)."""

import click


@click.command(name="demo")
def demo() -> None:
    """Not available yet."""
    raise click.UsageError("'aerialmtl demo' is not implemented yet")
