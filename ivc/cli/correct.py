"""``ivc correct LUT INPUT -o OUTPUT``: corrected poses, with their flags, in the input's format."""

from __future__ import annotations

import time

import click
import h5py
import numpy as np

from ivc import compiled, lut
from ivc import session as session_io
from ivc.cli.options import POSITIVE
from ivc.cli.paths import input_and_output
from ivc.cli.predict import check_tuning_rate, echo_timing, parse_horizon, requested_tuning
from ivc.cli.tracker import tracker_option, with_tracker
from ivc.collect.checks import rate_warning
from ivc.collect.plus import is_plus_sequence, read_plus, write_plus
from ivc.collect.replay import read_csv_columns, write_csv
from ivc.correct import Corrector, describe
from ivc.correct.reported import PoseCorrector
from ivc.correct.solver import (
    HIGH_RESIDUAL,
    INVALID_INPUT,
    LOW_PRECISION,
    MAX_RESIDUAL,
    NOT_CONVERGED,
    OUTSIDE,
    Correction,
)
from ivc.lut.build import file_digest
from ivc.pose.tracker_solver import SOLVERS
from ivc.predict import DEFAULT_FILTER, FILTERS, Tuning
from ivc.predict.steps import predicted_step
from ivc.session import Session, Step
from ivc.table.grid import INTERPOLATIONS
from ivc.units import LENGTH_UNITS

#: the name of the corrected transforms added to a PLUS sequence
PLUS_CORRECTED = "{tool}To{tracker}Ivc"
#: free-space steps: nothing to correct there
_FREE_SPACE = ("cube_calibration", "wand_calibration")


def corrected_step(step: Step, out: Correction, lut_file: str) -> Step:
    """The step with its reported poses replaced by the corrected ones (signals kept as measured)."""
    attrs = dict(step.attrs, corrected_with=str(lut_file))
    return Step(step.time, step.signal, out.position, out.quaternion, step.valid_mask, step.sample_rate_hz,
                step.sensor_ids, f"{step.description} (corrected by ivc)".strip(), attrs)


def _predicted(step: Step, out: Correction, name: str, horizon: float, tune: bool, tuning: Tuning | None = None,
               tuning_file: str | None = None) -> Step:
    """Corrected orientations predicted ``horizon`` s ahead from the trusted (unflagged) samples
    (:func:`ivc.predict.steps.predicted_step`), with the stream's timing on stderr."""
    echo_timing(f"{step.description or 'step'} (trusted samples)", step, out.ok)
    predicted, used = predicted_step(step, name, horizon, tune, tuning, tuning_file, valid=out.ok)
    if tune and used is not None:
        click.echo(used.summary())
    return predicted


def _correct_step(table, step: Step, hemisphere: str, interpolation: str, max_residual: float,
                  tracker: str | None, precision: dict | None = None) -> Correction:
    """A step's corrections: from its signals when it has them, else from its reported poses.
    ``precision``: the Corrector's precision keywords (``precision``, ``max_precision``, ``signal_noise``)."""
    if step.signal is not None:
        return Corrector(table, hemisphere, interpolation, max_residual, **(precision or {})).batch(
            step.signal, step.valid_mask)
    if precision:
        raise click.UsageError("--precision and --max-precision predict a pose's precision from its signal's "
                               "noise: the input holds reported poses only")
    return PoseCorrector(table, hemisphere, interpolation, tracker).batch(step.position, step.quaternion,
                                                                         step.valid_mask)


def csv_output_columns(kept: dict[str, np.ndarray], added: dict[str, np.ndarray]) -> tuple[dict, dict[str, str]]:
    """The extra columns of a corrected CSV: the input's own (``kept``) then ivc's (``added``); an input
    column whose name ivc uses is kept as ``input_<name>``. Returns (columns, {old name: new name})."""
    out, renamed = {}, {}
    for name, values in kept.items():
        new = name
        while new in added or new in out:
            new = f"input_{new}"
        if new != name:
            renamed[name] = new
        out[new] = values
    return {**out, **added}, renamed


def precision_columns(out: Correction) -> dict[str, np.ndarray]:
    """The predicted-precision CSV columns of a correction (none when it was not predicted)."""
    if out.precision is None:
        return {}
    return {"precision_mm": 1000 * out.precision, "orientation_precision_mrad": 1000 * out.orientation_precision}


def _summary(name: str, out: Correction) -> str:
    flags = out.flags.reshape(-1)
    counts = {describe(int(v)): int(n) for v, n in zip(*np.unique(flags[flags != 0], return_counts=True), strict=True)}
    text = f"{name}: {flags.size} samples, {int(np.sum(flags == 0))} corrected"
    text += "".join(f"; {n} {k}" for k, n in counts.items())
    trusted = flags == 0
    if out.precision is not None and trusted.any():
        predicted = 1000 * out.precision.reshape(-1)[trusted]
        text += (f"; predicted precision of the trusted poses {np.median(predicted):.3g} mm median, "
                 f"{np.percentile(predicted, 95):.3g} mm p95")
    return text


def _warn(advice: str | None) -> None:
    if advice:
        click.echo(f"warning: {advice}", err=True)


def _cold_note() -> None:
    """Say so when a small input ran the kernels' uncompiled forms (ivc.compiled): same results, but the next
    large input will compile them."""
    if compiled.used:
        click.echo("note: the compiled kernels are not in the cache yet (first run after an install), so this "
                   "small input ran their NumPy or interpreted forms (same results); `ivc warmup` compiles them "
                   "once", err=True)


def correction_advice(out: Correction, max_residual: float, pose_only: bool = False) -> str | None:
    """What to check when most valid samples carry one flag; None when most are trusted."""
    flags = out.flags.reshape(-1)
    valid = (flags & INVALID_INPUT) == 0
    if not valid.any():
        return "every sample is marked invalid or is not finite in the input: nothing to correct"
    if np.mean(flags[valid] == 0) >= 0.5:
        return None
    share = {bit: float(np.mean((flags[valid] & bit) != 0))
             for bit in (OUTSIDE, HIGH_RESIDUAL, NOT_CONVERGED, LOW_PRECISION)}
    bit = max(share, key=share.get)
    percent = f"{100 * share[bit]:.0f}% of the valid samples"
    if bit == OUTSIDE:
        return (f"{percent} lie outside the table's mapped volume: sweep the wand there and fit again "
                "(`ivc report` shows the coverage)")
    if bit == HIGH_RESIDUAL and pose_only:
        return (f"{percent} are reported poses the table's map does not produce (or not uniquely): was this "
                "recorded in the mapped room, with the source where it was when the table was fitted, in the "
                "table's hemisphere, and with the tracker solver the table assumes (--tracker)?")
    if bit == HIGH_RESIDUAL:
        median = float(np.median(out.residual.reshape(-1)[valid]))
        return (f"{percent} do not fit the table's field (median residual {median:.2g}, gate --max-residual "
                f"{max_residual:g}): was this recorded in the mapped room, with the source where it was when "
                "the table was fitted, and in the table's hemisphere?")
    if bit == LOW_PRECISION:
        return (f"{percent} are predicted less precise than --max-precision: the tracker's noise allows no better "
                "that far from the source; loosen the limit, or average frames of a static sensor")
    return (f"{percent} did not converge: check the hemisphere (--hemisphere for a CSV) and that the signals "
            "are in the tracker's units")


@click.command()
@click.argument("lut_file", type=click.Path(dir_okay=False))
@click.argument("input_file", type=click.Path(dir_okay=False), required=False)
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="Corrected output: a session .h5 or a .csv, as the input.")
@click.option("--step", "steps", multiple=True, help="Session input: step(s) to correct (default: every step "
              "recorded in the distorted volume).")
@click.option("--interpolation", type=click.Choice(INTERPOLATIONS), default="cubic", show_default=True)
@click.option("--max-residual", type=POSITIVE, default=MAX_RESIDUAL, show_default=True,
              help="Flag corrections whose rms(M − T S)/rms(S) exceeds this.")
@click.option("--hemisphere", help="Hemisphere of a CSV input (default: the table's).")
@click.option("--tracker", type=click.Choice(SOLVERS), help="Input of reported poses only: the tracker's own pose "
              "solver (default: the one the table was fitted for, else closed-form).")
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
@click.option("--rate-hz", type=POSITIVE, default=240.0, show_default=True,
              help="With --live --predict: the stream's sample rate.")
@click.option("--duration", type=POSITIVE, help="With --live: stop after this many seconds (default: until Ctrl-C).")
@click.option("--precision", "with_precision", is_flag=True,
              help="Write each pose's predicted RMS position and orientation error (from the tracker's signal noise "
                   "and the table's field; columns precision_mm, orientation_precision_mrad). Signal inputs only.")
@click.option("--max-precision", type=POSITIVE, metavar="MM",
              help="Flag (16) poses whose predicted RMS position error exceeds MM millimetres (implies --precision).")
@click.option("--signal-noise", type=POSITIVE, help="The tracker's white noise per signal entry, in signal units "
              "(default: what the table's fit measured on the session's static steps).")
@tracker_option
def correct(lut_file, input_file, output, steps, interpolation, max_residual, hemisphere, tracker, force, predictor,
            horizon, tune, tune_from, live_url, publish, length_unit, sensors, rate_hz, duration, with_precision,
            max_precision, signal_noise, tracker_file):
    """Correct the poses in INPUT_FILE (session .h5, recording .csv or PLUS sequence .igs.mha) with LUT_FILE.

    A PLUS sequence (.igs.mha, .seq.mha, .igs.nrrd) is written back with each
    <Tool>To<Tracker>Transform's correction added as <Tool>To<Tracker>IvcTransform, its
    status (OK = trusted) and <Tool>To<Tracker>IvcFlags, for Slicer's Sequences module.

    Every output sample carries flags: 0 = trusted; 1 outside the mapped volume, 2 not
    converged, 4 residual too high, 8 invalid input, 16 predicted precision over --max-precision
    (bits combine). Signals are used when
    the input has them; otherwise the reported poses are corrected directly, by inverting the
    tracker's pose-domain distortion (docs/lut.md): then 4 means a reported pose the map does
    not produce, or not uniquely. With --predict, the corrected orientations of trusted
    samples are then predicted --horizon ahead per sensor (positions stay corrected, unpredicted).

    With --live igtl://HOST:PORT, poses (TRANSFORM) or signal matrices (NDARRAY 3x3) streamed
    by a tracking server are corrected as they arrive and served on --publish (docs/live.md).
    """
    if (tune or tune_from) and not predictor:
        raise click.UsageError("--tune and --tune-from tune a prediction filter: give --predict NAME too")
    precision = None
    if with_precision or max_precision or signal_noise:
        precision = {"precision": True, "signal_noise": signal_noise,
                     "max_precision": None if max_precision is None else max_precision / 1000}
    if live_url:
        if tracker_file:
            raise click.UsageError("--tracker-model applies to recorded signals; a live stream must be in ideal units")
        if input_file or output:
            raise click.UsageError("--live reads from the network: give no INPUT_FILE or --output")
        if tune:
            raise click.UsageError("--tune needs the whole recording and cannot run on a live stream: tune from "
                                   "an earlier recording with --tune-from FILE")
        tuning = requested_tuning(predictor, tune, tune_from)
        if tuning is not None:
            check_tuning_rate(tuning, rate_hz, "the live stream (--rate-hz)")
        _live(lut_file, live_url, publish, length_unit, sensors, interpolation, max_residual, hemisphere, predictor,
              horizon, rate_hz, duration, tuning, tracker, precision)
        return
    if not input_file or not output:
        raise click.UsageError("give INPUT_FILE and -o OUTPUT (or --live igtl://HOST:PORT)")
    input_path, output_path = input_and_output(input_file, output, force,
                                               [("LUT_FILE", lut_file), ("--tune-from", tune_from)])
    delta = parse_horizon(horizon) if predictor else None
    tuning = requested_tuning(predictor, tune, tune_from)
    table = lut.read(lut_file)
    if is_plus_sequence(input_path):
        if tracker_file is not None:
            raise click.UsageError("--tracker-model applies to signal matrices; a PLUS sequence holds poses only")
        if precision:
            raise click.UsageError("--precision and --max-precision need signal matrices; a PLUS sequence holds "
                                   "poses only")
        _correct_plus(table, lut_file, input_path, output_path, hemisphere, interpolation, max_residual, predictor,
                      delta, tune, tuning, tune_from, tracker)
        return
    if session_io.is_recording_csv(input_path):
        if not session_io.is_recording_csv(output_path):
            raise click.UsageError("a CSV input is corrected into a CSV output (-o FILE.csv)")
        step, columns = read_csv_columns(input_path)
        _warn(rate_warning(step))
        if tracker_file is not None:
            step = with_tracker(Session(hemisphere or table.hemisphere, {"recording": step}), tracker_file
                                ).steps["recording"]
        out = _correct_step(table, step, hemisphere or table.hemisphere, interpolation, max_residual, tracker,
                            precision)
        fixed = corrected_step(step, out, lut_file)
        fixed.signal = None
        fixed.valid = out.flags == 0  # valid: the corrected pose is trusted (flags say why not)
        if predictor:
            fixed = _predicted(fixed, out, predictor, delta, tune, tuning, tune_from)
        extra, renamed = csv_output_columns(columns.extra, {"flags": out.flags, "residual": out.residual,
                                                            **precision_columns(out)})
        for old, new in renamed.items():
            _warn(f"the input's column {old!r} is written as {new!r} (ivc writes its own {old!r})")
        with session_io.atomic_path(output_path) as tmp:
            write_csv(fixed, tmp, extra, length_unit=columns.length_unit)
        click.echo(_summary(input_path.name, out))
        _warn(correction_advice(out, max_residual, step.signal is None))
        click.echo(f"wrote {output_path}")
        _cold_note()
        return
    data = session_io.read(input_path)
    names = list(steps) or [n for n in data.steps if n not in _FREE_SPACE]
    unknown = [n for n in names if n not in data.steps]
    if unknown:
        raise click.UsageError(f"{input_path} has no step {', '.join(unknown)} (it has {', '.join(data.steps)})")
    data = with_tracker(data, tracker_file, names)
    results = {}
    for name in names:
        step = data.steps[name]
        results[name] = _correct_step(table, step, data.hemisphere, interpolation, max_residual, tracker, precision)
        click.echo(_summary(name, results[name]))
        _warn(correction_advice(results[name], max_residual, step.signal is None))
    fixed = {n: corrected_step(data.steps[n], results[n], lut_file) for n in names}
    if predictor:
        fixed = {n: _predicted(fixed[n], results[n], predictor, delta, tune, tuning, tune_from) for n in names}
    corrected = Session(data.hemisphere, fixed,
                        {n: data.truth[n] for n in names if n in data.truth},
                        dict(data.attrs, corrected_with=str(lut_file), lut_sha256=file_digest(lut_file)))
    with session_io.atomic_path(output_path) as tmp:
        session_io.write(corrected, tmp, overwrite=True)
        with h5py.File(tmp, "a") as h5:
            for name, out in results.items():
                h5[f"steps/{name}/flags"] = out.flags
                h5[f"steps/{name}/flags"].attrs["meaning"] = (
                    "0 trusted; bits: 1 outside the mapped volume, 2 not converged, 4 residual too high (reported "
                    "poses: the map does not produce the pose, or not uniquely), 8 invalid input, 16 predicted "
                    "precision over the limit")
                h5[f"steps/{name}/residual"] = out.residual
                if out.precision is not None:
                    for key, values, unit in (("precision", out.precision, "m"),
                                              ("orientation_precision", out.orientation_precision, "rad")):
                        h5[f"steps/{name}/{key}"] = values
                        h5[f"steps/{name}/{key}"].attrs.update(
                            unit=unit, meaning="predicted RMS error of the corrected pose from the tracker's "
                                               "signal noise (Cramér-Rao bound of one frame)")
    click.echo(f"wrote {output_path}")
    _cold_note()


def _correct_plus(table, lut_file, input_path, output_path, hemisphere, interpolation, max_residual, predictor, delta,
                  tune, tuning, tune_from, tracker=None) -> None:
    """A PLUS sequence in; the same sequence with ``<Tool>To<Tracker>Ivc`` transforms added out (or a CSV, mm).

    A sequence holds reported poses only, so they are corrected through the pose path (the inverse of the
    tracker's pose-domain distortion), not from signals rebuilt from them."""
    same_format = output_path.suffix.lower() == input_path.suffix.lower()
    if not (same_format or session_io.is_recording_csv(output_path)):
        raise click.UsageError(f"a PLUS sequence is corrected into a sequence of the same format (-o "
                               f"FILE{input_path.suffix}) or a CSV (-o FILE.csv)")
    sequence = read_plus(input_path)
    step = sequence.step
    _warn(rate_warning(step))
    out = _correct_step(table, step, hemisphere or table.hemisphere, interpolation, max_residual, tracker)
    fixed = corrected_step(step, out, lut_file)
    fixed.valid = out.flags == 0
    if predictor:
        fixed = _predicted(fixed, out, predictor, delta, tune, tuning, tune_from)
    with session_io.atomic_path(output_path) as tmp:
        if session_io.is_recording_csv(output_path):
            write_csv(fixed, tmp, {"flags": out.flags, "residual": out.residual}, length_unit="mm")
        else:
            write_plus(sequence, tmp, {PLUS_CORRECTED: (fixed.position, fixed.quaternion, out.flags)})
    click.echo(_summary(input_path.name, out))
    _warn(correction_advice(out, max_residual, step.signal is None))
    if sequence.other_transforms:
        _warn(f"not corrected (not to the {sequence.tracker} frame): {', '.join(sequence.other_transforms)}")
    click.echo(f"wrote {output_path}")
    _cold_note()


def _live(lut_file, url, publish, length_unit, sensors, interpolation, max_residual, hemisphere, predictor, horizon,
          rate_hz, duration, tuning=None, tracker=None, precision=None) -> None:
    import logging

    from ivc.live import LiveCorrector, parse_url

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    table = lut.read(lut_file)
    # with --max-precision, signal samples whose predicted precision is over the limit are published flagged (16)
    corrector = Corrector(table, hemisphere or table.hemisphere, interpolation, max_residual, **(precision or {}))
    poses = PoseCorrector(table, hemisphere or table.hemisphere, interpolation, tracker)
    source = parse_url(url)
    host, _, port = publish.rpartition(":")
    if not host or not port.isdigit():
        raise click.UsageError(f"--publish wants HOST:PORT, got {publish!r}")
    click.echo("preparing the compiled correction (loaded from the cache; after an install it compiles in the "
               "background while the stream is corrected by its interpreted form; `ivc warmup` does it ahead)",
               err=True)
    start = time.perf_counter()
    live = LiveCorrector(corrector, source, (host, int(port)), length_unit=LENGTH_UNITS[length_unit],
                         predictor=predictor, horizon=parse_horizon(horizon) if predictor else 0.0, rate_hz=rate_hz,
                         tuning=tuning, pose_corrector=poses,
                         sensors=list(sensors) or None)
    state = "compiling in the background, interpreted until then" if live.compiling else "compiled"
    click.echo(f"ready in {time.perf_counter() - start:.1f} s ({state}): correcting {url} -> serving on "
               f"{live.publish_address[0]}:{live.publish_address[1]}", err=True)
    try:
        stats = live.run(duration)
    except KeyboardInterrupt:
        stats = live.stats
    latency = np.median(stats.latency_s) * 1e3 if stats.latency_s else float("nan")
    click.echo(f"received {stats.received}, corrected {stats.corrected}, flagged {stats.flagged}, out of order "
               f"{stats.out_of_order}, unknown {stats.unknown}, unusable {stats.rejected}, malformed bytes "
               f"{stats.garbage_bytes}, dropped for "
               f"slow clients {stats.dropped_for_slow_clients}, connections {stats.connections}; median processing "
               f"{latency:.3f} ms per batch", err=True)
