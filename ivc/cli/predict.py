"""``ivc predict``: predict orientation streams a horizon ahead, or benchmark the predictors on synthetic motion."""

from __future__ import annotations

import json
import re

import click
import numpy as np

from ivc import session as session_io
from ivc.cli.options import POSITIVE
from ivc.cli.paths import input_and_output
from ivc.cli.progress import ON_TERMINAL
from ivc.collect.checks import rate_warning
from ivc.collect.plus import is_plus_sequence, read_plus, write_plus
from ivc.collect.replay import read_csv, read_csv_columns, write_csv
from ivc.predict import FILTERS, TUNABLE, make
from ivc.predict.base import MAX_HORIZON
from ivc.predict.evaluate import (
    error_table,
    evaluate,
    horizon_table,
    overshoot_table,
    plot_error_vs_horizon,
    snr_table,
    velocity_table,
)
from ivc.predict.motion import MOTIONS, head_motion
from ivc.predict.tuning import Tuning, estimate, synthetic
from ivc.session import Session, Step

#: the benchmark's default filters: the thesis's, Kyger's and the linear ones
BENCHMARK_FILTERS = ("none", "dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3", "q-ekf", "mmae", "alpha-beta", "kinematic",
                     "poly1", "poly2")


def parse_horizon(text: str) -> float:
    """'50ms' or '0.05s' -> seconds; a bare number is refused (0.05 read as ms would be 50 µs)."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(ms|s)?\s*", str(text))
    if match and not match.group(2):
        raise click.BadParameter(f"{text!r} has no unit: write {text.strip()}ms or {text.strip()}s",
                                 param_hint="--horizon")
    if not match:
        raise click.BadParameter(f"{text!r}: give a horizon like 50ms or 0.05s")
    value = float(match.group(1)) * (1.0 if match.group(2) == "s" else 1e-3)
    if not 0 <= value <= MAX_HORIZON:
        raise click.BadParameter(f"{text!r}: the horizon must be between 0 and {MAX_HORIZON * 1e3:g} ms")
    return value


def tuning_from(path: str) -> Tuning:
    """A tuning (:mod:`ivc.predict.tuning`) from every orientation step of a recording .csv or session .h5.

    The steps are pooled as the thesis's composite set; they must share one sample rate.
    """
    steps = [read_csv(path)] if session_io.is_recording_csv(path) else list(session_io.read(path).steps.values())
    usable = [s for s in steps if s.quaternion is not None and s.sample_rate_hz]
    if not usable:
        raise click.UsageError(f"{path} has no step with orientations and a sample rate to tune from")
    rates = sorted({float(s.sample_rate_hz) for s in usable})
    if len(rates) > 1:
        raise click.UsageError(f"{path} has steps at {', '.join(f'{r:g}' for r in rates)} Hz: tune from recordings "
                               "at one rate, the rate of the stream to predict")
    tuning = estimate([s.quaternion for s in usable], rates[0], valid=[s.valid_mask for s in usable])
    click.echo(f"--tune-from {path}:\n" + tuning.summary())
    return tuning


def requested_tuning(name: str, tune: bool, tune_from: str | None) -> Tuning | None:
    """The tuning of ``--tune-from`` (``--tune`` tunes later, per step), after checking the two options.

    Filters without a noise model to tune are predicted as they are, with a note that says so.
    """
    if tune and tune_from:
        raise click.UsageError("give --tune (from the input) or --tune-from FILE, not both")
    if (tune or tune_from) and name not in TUNABLE:
        click.echo(f"note: {name} has no noise model to tune (only {', '.join(TUNABLE)} have): predicting without "
                   "tuning", err=True)
        return None
    return tuning_from(tune_from) if tune_from else None


def check_tuning_rate(tuning: Tuning, rate_hz: float, what: str) -> None:
    """Refuse a tuning made at another rate than the stream's, in the words of the CLI's options."""
    if not tuning.matches_rate(rate_hz):
        raise click.UsageError(f"--tune-from is a recording at {tuning.rate_hz:g} Hz, {what} is at {rate_hz:g} Hz: "
                               "tune from a recording at the stream's rate")


def predicted_quaternions(step: Step, name: str, horizon: float, valid: np.ndarray | None = None,
                          tune: bool = False, tuning: Tuning | None = None) -> np.ndarray:
    """The step's orientations predicted ``horizon`` s ahead; samples without a prediction (the filter's first
    frames, invalid samples) keep the measured orientation. ``tune``: the filter's measurement and process noise
    are estimated from the step itself (:mod:`ivc.predict.tuning`); or ``tuning`` gives them."""
    if step.quaternion is None:
        raise click.UsageError("this input has no orientations (signals only): run `ivc correct` first")
    if not step.sample_rate_hz:
        raise click.UsageError("the input does not give its sample rate; pass --rate HZ")
    ok = step.valid_mask if valid is None else valid & step.valid_mask
    if tune and name in TUNABLE:
        tuning = estimate(step.quaternion, step.sample_rate_hz, valid=ok)
        click.echo(tuning.summary())
    elif tuning is not None:
        check_tuning_rate(tuning, step.sample_rate_hz, "the input")
    predicted = make(name, step.sample_rate_hz, tuning).predict(step.quaternion, horizon, ok)[0]
    return np.where(np.all(np.isfinite(predicted), axis=-1, keepdims=True), predicted, step.quaternion)


def prediction_attrs(step: Step, name: str, horizon: float, tune: bool, tuning_file: str | None) -> dict:
    """``step``'s attributes with the prediction's: the filter, the horizon (s) and how it was tuned."""
    attrs = dict(step.attrs, predicted_with=name, prediction_horizon_s=horizon,
                 tuned_from_input=bool(tune and name in TUNABLE))
    if tuning_file and name in TUNABLE:
        attrs["tuned_from"] = str(tuning_file)
    return attrs


def predicted_step(step: Step, name: str, horizon: float, tune: bool = False, tuning: Tuning | None = None,
                   tuning_file: str | None = None) -> Step:
    attrs = prediction_attrs(step, name, horizon, tune, tuning_file)
    quaternion = predicted_quaternions(step, name, horizon, tune=tune, tuning=tuning)
    return Step(step.time, None, step.position, quaternion, step.valid_mask, step.sample_rate_hz, step.sensor_ids,
                f"{step.description} (orientation predicted by ivc)".strip(), attrs)


def _predict_plus(input_path, output_path, name, delta, tune, tuning, tune_from, rate) -> None:
    """A PLUS sequence in; the sequence with ``<Tool>To<Tracker>Predicted`` transforms added (or a CSV, mm)."""
    if not (output_path.suffix.lower() == input_path.suffix.lower() or session_io.is_recording_csv(output_path)):
        raise click.UsageError(f"a PLUS sequence is predicted into a sequence of the same format (-o "
                               f"FILE{input_path.suffix}) or a CSV (-o FILE.csv)")
    sequence = read_plus(input_path)
    step = sequence.step
    if rate:
        step.sample_rate_hz = rate
    out = predicted_step(step, name, delta, tune, tuning, tune_from)
    with session_io.atomic_path(output_path) as tmp:
        if session_io.is_recording_csv(output_path):
            write_csv(out, tmp, length_unit="mm")
        else:
            write_plus(sequence, tmp, {"{tool}To{tracker}Predicted": (out.position, out.quaternion, None)})
    click.echo(f"{input_path.name}: {step.n_frames} frames x {step.n_sensors} sensors predicted "
               f"{delta * 1e3:g} ms ahead with {name}")
    click.echo(f"wrote {output_path}")


def run_compensators(seed: int, evaluations: int, as_json: bool) -> None:
    """Seed 003's designs (default, twist, hybrid) on synthetic 20 s yaw records; Table 1."""
    from tqdm import tqdm

    from ivc.predict.nasa import DEFAULT_W
    from ivc.predict.studies import compensator

    records = compensator.yaw_records(seed=seed)
    designs, counts = {"default": np.array(DEFAULT_W)}, {}
    for name in ("twist", "hybrid"):
        with tqdm(total=evaluations, desc=f"Powell: {name} design", unit="cost", leave=False,
                  disable=ON_TERMINAL) as bar:
            designs[name], result = compensator.optimise(name, records, max_evaluations=evaluations,
                                                         progress=bar.update)
        counts[name] = int(result.nfev)
    rows = {name: compensator.score(W, records).ratios for name, W in designs.items()}
    if as_json:
        click.echo(json.dumps({name: {"ratios": dict(zip(compensator.COLUMNS, rows[name], strict=True)),
                                      "W": designs[name].tolist(), "paper": compensator.PAPER_TABLE1[name]}
                               for name in designs}, indent=2))
        return
    click.echo(compensator.render_table1(rows, counts))
    for name, W in designs.items():
        click.echo(f"  W_r {name:<8}" + " ".join(f"{w:.1e}" for w in W))


def run_benchmark(motions, filters, frames, rate, seed, reference, plot, as_json, tune=False):
    from tqdm import tqdm

    results, runs = [], [(m, f) for m in motions for f in filters]
    recordings = {}
    tuning = synthetic(frames, rate, seed) if tune else None
    if tuning is not None and not as_json:
        click.echo(tuning.summary() + "\n")
    for motion, name in tqdm(runs, desc="benchmark", unit="run", leave=False, disable=ON_TERMINAL):
        if motion not in recordings:
            recordings[motion] = head_motion(motion, frames, rate, seed=seed)
        h = recordings[motion]
        truth = h.truth if reference == "truth" else None
        results.append(evaluate(make(name, rate, tuning), h.measured, rate, motion, truth=truth, omega_true=h.omega))
    if as_json:
        click.echo(json.dumps([{"filter": r.name, "motion": r.motion, "horizons_ms": r.horizons_ms.tolist(),
                                "rows": r.rows, "velocity": r.velocity} for r in results], indent=1))
    else:
        click.echo(f"synthetic head motion, {frames} frames at {rate:g} Hz, seed {seed}; errors against the "
                   f"{'noiseless truth' if reference == 'truth' else 'time-shifted measurements'}; seed-001 filters "
                   f"{'tuned on the set above' if tune else 'with the thesis values (Table 3, eq. 67, Table 10)'}\n")
        click.echo(overshoot_table(results) + "\n")
        click.echo(error_table(results) + "\n")
        for m in motions:
            click.echo(horizon_table(results, m) + "\n")
        click.echo(velocity_table(results) + "\n")
        click.echo(snr_table(results))
    if plot:
        plot_error_vs_horizon(results, plot)
        click.echo(f"wrote {plot}")


@click.command()
@click.argument("input_file", required=False, type=click.Path(dir_okay=False))
@click.option("--filter", "filters", multiple=True, type=click.Choice(list(FILTERS)),
              help="Predictor (default mmdq2). With --benchmark: repeat to choose several (default: all but nasa-ekf).")
@click.option("--horizon", default="50ms", show_default=True, help="How far ahead, with its unit: 50ms or 0.05s.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), help="Output: session .h5 or .csv, as the input.")
@click.option("--step", "steps", multiple=True, help="Session input: step(s) to predict (default: all).")
@click.option("--rate", type=POSITIVE, help="Sample rate (Hz) of a CSV without a usable time column.")
@click.option("--force", is_flag=True, help="Replace OUTPUT if it exists (never the input).")
@click.option("--benchmark", is_flag=True, help="Evaluate predictors on synthetic head motion and print the "
              "thesis's tables (horizons 0-117 ms).")
@click.option("--motion", "motions", multiple=True, type=click.Choice(MOTIONS), help="Benchmark motion(s).")
@click.option("--frames", type=int, default=12_000, show_default=True, help="Benchmark frames per motion.")
@click.option("--bench-rate", type=click.Choice(["120", "240"]), default="120", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--reference", type=click.Choice(["measured", "truth"]), default="measured", show_default=True,
              help="Benchmark reference: time-shifted measurements (the thesis) or the noiseless truth.")
@click.option("--plot", type=click.Path(dir_okay=False), help="Benchmark: write the error-vs-horizon PNG here.")
@click.option("--json", "as_json", is_flag=True, help="Benchmark: print the figures as JSON.")
@click.option("--tune", is_flag=True, help="Tune the seed-001 filters (q-ekf, dqekf-*, mmdq*) by the thesis's "
              "procedure (measurement noise from the data, process noise at each model's λ) instead of using the "
              "thesis's values: from each input step itself, or with --benchmark from a separate synthetic "
              "tuning set. Prints the estimates.")
@click.option("--tune-from", "tune_from", type=click.Path(exists=True, dir_okay=False),
              help="As --tune, from another recording (.csv) or session (.h5, every step with orientations), "
              "at the input's sample rate: the thesis's separate tuning set.")
@click.option("--compensators", is_flag=True, help="Seed 003: optimise the 10-state EKF's process noise by Powell's "
              "method for the twist and hybrid costs on synthetic yaw records, and print Table 1.")
@click.option("--evaluations", type=int, default=1500, show_default=True,
              help="With --compensators: cost evaluations per design at most.")
def predict(input_file, filters, horizon, output, steps, rate, force, benchmark, motions, frames, bench_rate, seed,
            reference, plot, as_json, tune, tune_from, compensators, evaluations):
    """Predict the orientations in INPUT_FILE (session .h5 or recording .csv) a horizon ahead.

    The output holds, at each frame's time stamp, the orientation predicted for time +
    horizon from that frame and the ones before it; positions are copied unchanged. Samples
    the filter cannot predict yet (its first frames) or that are invalid keep their measured
    orientation. `ivc predict --benchmark` instead evaluates the predictors on synthetic head
    motion and prints the thesis's tables (Tables 5-6, 11, 12-15 layouts, and the SNR of Figs. 16-17).
    """
    if tune_from and (benchmark or compensators):
        raise click.UsageError("--tune-from tunes the prediction of an INPUT_FILE; --benchmark --tune tunes on "
                               "synthetic data")
    if compensators:
        if evaluations < 1:
            raise click.BadParameter("must be at least 1", param_hint="--evaluations")
        run_compensators(seed, evaluations, as_json)
        return
    if benchmark:
        if frames < 1000:
            raise click.BadParameter("use at least 1000 frames", param_hint="--frames")
        run_benchmark(list(motions) or list(MOTIONS), list(filters) or list(BENCHMARK_FILTERS), frames,
                      float(bench_rate), seed, reference, plot, as_json, tune)
        return
    if input_file is None or output is None:
        raise click.UsageError("give INPUT_FILE and -o OUTPUT (or --benchmark)")
    if len(filters) > 1:
        raise click.UsageError("predict a stream with one --filter")
    name = filters[0] if filters else "mmdq2"
    delta = parse_horizon(horizon)
    input_path, output_path = input_and_output(input_file, output, force, [("--tune-from", tune_from)])
    tuning = requested_tuning(name, tune, tune_from)
    if is_plus_sequence(input_path):
        _predict_plus(input_path, output_path, name, delta, tune, tuning, tune_from, rate)
        return
    if session_io.is_recording_csv(input_path):
        if not session_io.is_recording_csv(output_path):
            raise click.UsageError("a CSV input is predicted into a CSV output (-o FILE.csv)")
        step, columns = read_csv_columns(input_path, rate)
        warning = rate_warning(step) if rate is None else None
        if warning:
            click.echo(f"warning: {warning}", err=True)
        out = predicted_step(step, name, delta, tune, tuning, tune_from)
        with session_io.atomic_path(output_path) as tmp:
            write_csv(out, tmp, columns.extra, length_unit=columns.length_unit)
        click.echo(f"{input_path.name}: {step.n_frames} frames x {step.n_sensors} sensors predicted "
                   f"{delta * 1e3:g} ms ahead with {name}")
        click.echo(f"wrote {output_path}")
        return
    data = session_io.read(input_path)
    names = list(steps) or list(data.steps)
    unknown = [n for n in names if n not in data.steps]
    if unknown:
        raise click.UsageError(f"{input_path} has no step {', '.join(unknown)} (it has {', '.join(data.steps)})")
    out_steps = {}
    for n in names:
        step = data.steps[n]
        if rate and not step.sample_rate_hz:
            step.sample_rate_hz = rate
        out_steps[n] = predicted_step(step, name, delta, tune, tuning, tune_from)
        click.echo(f"{n}: {step.n_frames} frames x {step.n_sensors} sensors predicted {delta * 1e3:g} ms ahead")
    predicted = Session(data.hemisphere, out_steps, {n: data.truth[n] for n in names if n in data.truth},
                        dict(data.attrs, predicted_with=name, prediction_horizon_s=delta))
    with session_io.atomic_path(output_path) as tmp:
        session_io.write(predicted, tmp, overwrite=True)
    click.echo(f"wrote {output_path}")
