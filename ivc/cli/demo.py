"""``ivc demo``: the whole pipeline on a simulated distorted room, in one command (see :mod:`ivc.demo`)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import click

from ivc import demo as demo_run
from ivc import lut
from ivc.cli.collect import SimulatorProgress, summary
from ivc.cli.evaluate import render_table
from ivc.cli.fit import render_fit
from ivc.cli.options import SIM_FRAMES
from ivc.cli.progress import StageBars
from ivc.session import extension_steps


@click.command()
@click.option("--scene", default="default", show_default=True, help="Built-in scene name or a scene .toml file.")
@click.option("--seed", type=int, default=0, show_default=True, help="Simulator seed.")
@click.option("--sweep-frames", type=SIM_FRAMES, default=100_000, show_default=True, help="Frames of the wand sweep.")
@click.option("--check-frames", type=SIM_FRAMES, default=10_000, show_default=True, help="Random check poses.")
@click.option("--method", type=click.Choice(lut.METHODS), default="harmonic", show_default=True)
@click.option("--keep", "keep_dir", type=click.Path(file_okay=False),
              help="Keep the session and table in this directory (default: a temporary one, removed).")
@click.option("--pose-only", is_flag=True, help="Drop the signals after collecting, as a tracker that reports poses "
              "only would: fit and correct from the reported poses alone.")
@click.option("--force", is_flag=True, help="With --keep: replace files from an earlier demo.")
def demo(scene, seed, sweep_frames, check_frames, method, pose_only, keep_dir, force):
    """Simulate a distorted room, collect the protocol, fit the map, and compare corrected with uncorrected poses."""
    start = time.perf_counter()
    sim = SimulatorProgress(scene, seed)

    def stage(name: str, made: demo_run.DemoResult) -> None:
        if name == "collect":
            into = f" into {made.session_file}" if keep_dir else ""  # a temporary file is deleted: no path to print
            click.echo(f"1/3 collect: simulating scene {scene!r} (seed {seed}){into}", err=True)
        elif name == "fit":
            for step in made.session.steps:
                click.echo(summary(step, made.session.steps[step], made.session.truth.get(step)))
            click.echo(f"wrote {made.session_file}" if keep_dir else "collected the protocol (temporary session)")
            kind = ("whole-volume look-up table (extension sweeps, joint solve)"
                    if extension_steps(made.session.steps) else f"{method} look-up table")
            click.echo(f"2/3 fit: {kind}" + (" from reported poses alone (signals dropped)" if pose_only else ""),
                       err=True)
        else:
            click.echo(render_fit(made.table, made.fit_seconds))
            click.echo("3/3 evaluate: correcting the check poses", err=True)

    with tempfile.TemporaryDirectory(prefix="ivc-demo-") as scratch:
        folder = Path(keep_dir) if keep_dir else Path(scratch)
        with sim.protocol_progress(sim.scene.hemisphere) as on_step, StageBars("sample") as bars:
            result = demo_run.run(simulator=sim.simulator, sweep_frames=sweep_frames, check_frames=check_frames,
                                  method=method, folder=folder, force=force, on_step=on_step, fit_progress=bars,
                                  pose_only=pose_only,
                                  on_stage=stage)
        click.echo("")
        click.echo(render_table(result.report))
        click.echo("")
        where = f"; files kept in {folder}" if keep_dir else ""
        click.echo(f"ivc demo finished in {time.perf_counter() - start:.0f} s{where}")
        if keep_dir:
            click.echo(f"figures and an HTML page: ivc report {result.session_file} {result.table_file} "
                       f"-o {folder / 'report'}")
