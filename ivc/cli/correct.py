"""``ivc correct LUT INPUT -o OUTPUT``: corrected poses, with their flags, in the input's format.

The command parses its options into :class:`ivc.app.correct.CorrectOptions`, calls :func:`ivc.correct_file` (or
sets up :func:`ivc.live_corrector` with ``--live``) and prints what they report.
"""

from __future__ import annotations

import time

import click
import numpy as np

from ivc import compiled
from ivc.app.correct import CorrectOptions, LiveOptions, correct_file, live_corrector
from ivc.cli.flags import echo_report, usage_errors
from ivc.cli.options import POSITIVE, RATE_HZ, solver_option
from ivc.cli.predict import parse_horizon
from ivc.cli.tracker import tracker_option
from ivc.correct.precision import DEFAULT
from ivc.correct.solver import MAX_RESIDUAL
from ivc.igtl import parse_url
from ivc.predict import DEFAULT_FILTER, FILTERS
from ivc.table.grid import INTERPOLATIONS
from ivc.units import LENGTH_UNITS


def _cold_note() -> None:
    """Say so when a small input ran the kernels' uncompiled forms (ivc.compiled): same results, but the next
    large input will compile them."""
    if compiled.used:
        click.echo("note: the compiled kernels are not in the cache yet (first run after an install), so this "
                   "small input ran their NumPy or interpreted forms (same results); `ivc warmup` compiles them "
                   "once", err=True)


@click.command()
@click.argument("lut_file", type=click.Path(dir_okay=False))
@click.argument("input_file", type=click.Path(dir_okay=False), required=False)
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="Corrected output: a session .h5 or a .csv, as the input.")
@click.option("--step", "steps", multiple=True, help="Session input: step(s) to correct (default: every step "
              "recorded in the distorted volume).")
@click.option("--interpolation", type=click.Choice(INTERPOLATIONS), default="cubic", show_default=True)
@click.option("--max-residual", type=POSITIVE, default=None,
              help="Flag corrections whose rms(M − T S)/rms(S) exceeds this (default: a limit per pose, a multiple "
              "of the residual the table's cross-validated model error and the signal noise explain there; "
              f"{MAX_RESIDUAL:g} for a table that records neither).")
@click.option("--hemisphere", help="Hemisphere of a CSV input (default: the table's).")
@solver_option("Input of reported poses only: the tracker's own pose solver (default: the one the table was fitted "
               "for, else closed-form).")
@click.option("--force", is_flag=True, help="Replace OUTPUT if it exists (never the input).")
@click.option("--predict", "predictor", type=click.Choice(list(FILTERS)), is_flag=False, flag_value=DEFAULT_FILTER,
              help=f"Then predict each sensor's corrected orientation ahead with this filter (see `ivc predict`); "
              f"--predict alone: {DEFAULT_FILTER}.")
@click.option("--horizon", default="50ms", show_default=True, help="Prediction horizon with --predict.")
@click.option("--tune", is_flag=True, help="With --predict: tune Himberg's filters (q-ekf, dqekf-*, mmdq*) to each "
              "corrected step's trusted samples (see `ivc predict --tune`). Not with --live.")
@click.option("--tune-from", "tune_from", type=click.Path(exists=True, dir_okay=False),
              help="With --predict: tune the filter from this recording (.csv) or session (.h5) instead, "
              "at the stream's rate; works with --live.")
@click.option("--live", "live_url", metavar="igtl://HOST:PORT",
              help="Correct a live OpenIGTLink stream from this tracking server instead of INPUT_FILE.")
@click.option("--publish", default="127.0.0.1:18945", show_default=True, metavar="HOST:PORT",
              help="With --live: serve the corrected poses here (port 0: any free port).")
@click.option("--unit", "length_unit", type=click.Choice(list(LENGTH_UNITS)), default="mm", show_default=True,
              help="With --live: length unit of the stream's translations (PLUS and Slicer use mm).")
@click.option("--sensor", "sensors", multiple=True, help="With --live: correct only these device names "
              "(default: every device that sends TRANSFORM or NDARRAY messages).")
@click.option("--rate-hz", type=RATE_HZ, default=240.0, show_default=True,
              help="With --live --predict: the stream's sample rate.")
@click.option("--duration", type=POSITIVE, help="With --live: stop after this many seconds (default: until Ctrl-C).")
@click.option("--precision/--no-precision", "with_precision", default=True, show_default=True,
              help="Predict each pose's RMS position and orientation error from the tracker's signal noise (columns "
                   "precision_mm, orientation_precision_mrad), for signals and reported poses, wherever the noise "
                   "is known (the table's fit measures it).")
@click.option("--max-precision", "max_precision", metavar="MM|none",
              help="Flag (16) poses predicted less precise than MM millimetres RMS (default: 0.8 mm wherever the "
                   "tracker's noise is known; docs/trust.md says why); 'none' turns the gate off.")
@click.option("--signal-noise", type=POSITIVE, help="The tracker's white noise per signal entry, in signal units "
              "(default: what the table's fit measured on the session's static steps).")
@click.option("--allow-corrected", is_flag=True, help="Take an INPUT_FILE that is ivc's corrected output (a session "
              "with corrected_with, a CSV with flags and residual columns): refused otherwise, as its poses would be "
              "corrected twice.")
@click.option("--rigid-body", "rigid_body", type=click.Path(exists=True, dir_okay=False),
              help="The sensors are fixed to one body: a session whose wand_calibration step holds them in free space, "
                   "or a JSON file of their poses ({\"positions\": [[x, y, z], ...] m, \"quaternions\": [[w, x, y, "
                   "z], ...]}). A trusted sensor the body's other sensors disagree with is flagged 4, and a reported "
                   "pose the map produces twice is trusted where the body puts it on one branch (docs/trust.md). "
                   "In a session: the wand's steps; live: the --sensor names given, in the body's order.")
@tracker_option
def correct(lut_file, input_file, output, steps, interpolation, max_residual, hemisphere, solver, force, predictor,
            horizon, tune, tune_from, live_url, publish, length_unit, sensors, rate_hz, duration, with_precision,
            max_precision, signal_noise, allow_corrected, rigid_body, tracker_file):
    """Correct the poses in INPUT_FILE (session .h5, recording .csv or PLUS sequence .igs.mha) with LUT_FILE.

    A PLUS sequence (.igs.mha, .seq.mha, .igs.nrrd) is written back with each
    <Tool>To<Tracker>Transform's correction added as <Tool>To<Tracker>IvcTransform, its
    status (OK = trusted) and <Tool>To<Tracker>IvcFlags, for Slicer's Sequences module.

    Every output sample carries flags: 0 = trusted; 1 outside the mapped volume, 2 not
    converged, 4 residual too high, 8 invalid input, 16 predicted precision over --max-precision
    (default 0.8 mm RMS, wherever the tracker's noise is known; bits combine). Signals are used when
    the input has them; otherwise the reported poses are corrected directly, by inverting the
    tracker's pose-domain distortion (docs/lut.md): then 4 means a reported pose the map does
    not produce, or not uniquely. With --predict, the corrected orientations of trusted
    samples are then predicted --horizon ahead per sensor (positions stay corrected, unpredicted).

    With --live igtl://HOST:PORT, poses (TRANSFORM) or signal matrices (NDARRAY 3x3) streamed
    by a tracking server are corrected as they arrive and served on --publish (docs/live.md).
    """
    options = CorrectOptions(steps=steps, interpolation=interpolation, max_residual=max_residual, hemisphere=hemisphere,
                             solver=solver, precision=with_precision, signal_noise=signal_noise,
                             max_precision=precision_limit(max_precision),
                             tracker_model=tracker_file, predictor=predictor, tune=tune, tune_from=tune_from,
                             overwrite=force, allow_corrected=allow_corrected, rigid_body=rigid_body)
    with usage_errors("correct"):
        options.check()
        if live_url:
            if input_file or output:
                raise click.UsageError("--live reads from the network: give no INPUT_FILE or --output")
            host, _, port = publish.rpartition(":")
            if not host or not port.isdigit() or int(port) > 65535:
                raise click.UsageError(f"--publish wants HOST:PORT with a port from 0 to 65535, got {publish!r}")
            parse_url(live_url)  # its port checked before the table is read
            if predictor:
                options.horizon = parse_horizon(horizon)
            _live(lut_file, live_url, options, LiveOptions((host, int(port)), length_unit, sensors, rate_hz), duration)
            return
        if not input_file or not output:
            raise click.UsageError("give INPUT_FILE and -o OUTPUT (or --live igtl://HOST:PORT)")
        if predictor:
            options.horizon = parse_horizon(horizon)
        result = correct_file(lut_file, input_file, output, options, report=echo_report("correct"))
    click.echo(f"wrote {result.output}")
    _cold_note()


def precision_limit(text: str | None) -> float | str | None:
    """``--max-precision``: millimetres to metres; ``none`` turns the gate off; not given: the library's default."""
    if text is None:
        return DEFAULT
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise click.BadParameter(f"{text!r}: give a length in mm, or 'none'", param_hint="--max-precision") from None
    if not (value > 0 and value < float("inf")):
        raise click.BadParameter(f"{text!r}: give a positive length in mm, or 'none'", param_hint="--max-precision")
    return value / 1000


def _live(lut_file, url, options: CorrectOptions, live: LiveOptions, duration: float | None) -> None:
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    click.echo("preparing the compiled correction (loaded from the cache; after an install it compiles in the "
               "background while the stream is corrected by its interpreted form; `ivc warmup` does it ahead)",
               err=True)
    start = time.perf_counter()
    # samples predicted less precise than --max-precision are published flagged (16), with their precision
    corrector = live_corrector(lut_file, url, options, live, report=echo_report("correct"))
    state = "compiling in the background, interpreted until then" if corrector.compiling else "compiled"
    click.echo(f"ready in {time.perf_counter() - start:.1f} s ({state}): correcting {url} -> serving on "
               f"{corrector.publish_address[0]}:{corrector.publish_address[1]}", err=True)
    try:
        stats = corrector.run(duration)
    except KeyboardInterrupt:
        stats = corrector.stats
    latency = (f"median processing {np.median(stats.latency_s) * 1e3:.3f} ms per batch" if stats.latency_s
               else "no batch processed")
    click.echo(f"received {stats.received}, corrected {stats.corrected}, flagged {stats.flagged}, out of order "
               f"{stats.out_of_order}, unknown {stats.unknown}, unusable {stats.rejected}, malformed bytes "
               f"{stats.garbage_bytes}, dropped for "
               f"slow clients {stats.dropped_for_slow_clients}, connections {stats.connections}; {latency}", err=True)
    if stats.connections == 0:
        raise click.ClickException(f"never reached a tracking server at {url}: nothing was corrected. Is the server "
                                   "(PLUS, 3D Slicer, `ivc serve`) running, and are its host and port these?")
