"""``ivc warmup``: compile the numba kernels now, so the first real command does not wait for them."""

from __future__ import annotations

import click

from ivc.warmup import GROUPS, cache_location, warm_up


@click.command()
@click.option("--only", "groups", multiple=True, type=click.Choice(GROUPS),
              help="Warm only these groups (default: all): correct (ivc correct, --live), fit (ivc fit, demo).")
def warmup(groups):
    """Compile (or load from the cache) the compiled kernels the commands use.

    The first run after an install compiles them (about a minute on 2 cores); later runs load
    them from the cache in a second or two.
    """
    click.echo(f"numba cache: {cache_location()}", err=True)
    for group, seconds in warm_up(groups or GROUPS, progress=lambda g: click.echo(f"{g}: ...", err=True)):
        click.echo(f"{group}: ready in {seconds:.1f} s")
