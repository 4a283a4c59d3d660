"""``ivc demo``: the whole pipeline on a simulated distorted room, in one command."""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import click

from ivc import lut
from ivc import session as session_io
from ivc.cli.collect import collect
from ivc.cli.evaluate import render_table
from ivc.cli.fit import render_fit
from ivc.cli.progress import StageBars
from ivc.correct.evaluate import evaluate
from ivc.lut.build import FitOptions


def without_signals(data: session_io.Session) -> session_io.Session:
    """The session with every step's signal matrices removed (reported poses kept)."""
    steps = {name: replace(step, signal=None) for name, step in data.steps.items()}
    return session_io.Session(data.hemisphere, steps, data.truth, data.attrs)


@click.command()
@click.option("--scene", default="default", show_default=True, help="Built-in scene name or a scene .toml file.")
@click.option("--seed", type=int, default=0, show_default=True, help="Simulator seed.")
@click.option("--sweep-frames", type=int, default=100_000, show_default=True, help="Frames of the wand sweep.")
@click.option("--check-frames", type=int, default=10_000, show_default=True, help="Random check poses.")
@click.option("--method", type=click.Choice(lut.METHODS), default="harmonic", show_default=True)
@click.option("--keep", "keep_dir", type=click.Path(file_okay=False),
              help="Keep the session and table in this directory (default: a temporary one, removed).")
@click.option("--pose-only", is_flag=True, help="Drop the signals after collecting, as a tracker that reports poses "
              "only would: fit and correct from the reported poses alone.")
@click.option("--force", is_flag=True, help="With --keep: replace files from an earlier demo.")
@click.pass_context
def demo(ctx, scene, seed, sweep_frames, check_frames, method, pose_only, keep_dir, force):
    """Simulate a distorted room, collect the protocol, fit the map, and compare corrected with uncorrected poses."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ivc-demo-") as scratch:
        folder = Path(keep_dir) if keep_dir else Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        session_file, table_file = folder / "demo.h5", folder / "demo_lut.h5"
        for existing in (session_file, table_file):
            if existing.exists() and not force:
                raise FileExistsError(f"{existing} exists; pass --force to replace it, or --keep another directory")
        click.echo(f"1/3 collect: simulating scene {scene!r} (seed {seed}) into {session_file}", err=True)
        ctx.invoke(collect, step="protocol", source=f"sim:{scene}", output=str(session_file), frames=None,
                   sweep_frames=sweep_frames, check_frames=check_frames, seed=seed, hemisphere=None, rate=None,
                   declared_position=None, declared_quaternion=None, force=force)
        data = session_io.read(session_file)
        if pose_only:
            data = without_signals(data)
            session_io.write(data, session_file, overwrite=True)
            click.echo("   signals dropped: the session now holds reported poses only", err=True)
        click.echo(f"2/3 fit: {method} look-up table" + (" from reported poses" if pose_only else ""), err=True)
        fit_start = time.perf_counter()
        with StageBars("sample") as bars:
            table = lut.fit_lut(data, FitOptions(method=method), source=session_file, progress=bars)
        lut.write(table, table_file, overwrite=force)
        click.echo(render_fit(table, time.perf_counter() - fit_start))
        click.echo("3/3 evaluate: correcting the check poses", err=True)
        report = evaluate(table, data)
        click.echo("")
        click.echo(render_table(report))
        click.echo("")
        where = f"; files kept in {folder}" if keep_dir else ""
        click.echo(f"ivc demo finished in {time.perf_counter() - start:.0f} s{where}")
        if keep_dir:
            click.echo(f"figures and an HTML page: ivc report {session_file} {table_file} -o {folder / 'report'}")
