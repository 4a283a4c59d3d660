"""``ivc predict``: predict orientation streams a horizon ahead (:func:`ivc.predict_file`), score the predictors on a
recording, or benchmark them on synthetic motion."""

from __future__ import annotations

import json
import re
from pathlib import Path

import click
import numpy as np

from ivc import session as session_io
from ivc.app.correct import timing_text
from ivc.app.paths import atomic_figure, check_plot
from ivc.app.predict import PredictOptions, predict_file
from ivc.cli.flags import echo_report, usage_errors
from ivc.cli.options import RATE_HZ, SEED
from ivc.cli.progress import ON_TERMINAL
from ivc.collect.imports import read_recording, sniff
from ivc.predict import DEFAULT_FILTER, FILTERS, make
from ivc.predict.base import MAX_HORIZON
from ivc.predict.motion import MOTIONS, head_motion
from ivc.predict.recording import Score
from ivc.predict.studies.evaluate import (
    error_table,
    evaluate,
    horizon_table,
    overshoot_table,
    plot_error_vs_horizon,
    snr_table,
    velocity_table,
)
from ivc.predict.tuning import synthetic
from ivc.session import Step

#: the benchmark's default filters: the thesis's, Kyger's and the linear ones
BENCHMARK_FILTERS = ("none", "auto", "direct", "dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3", "q-ekf", "mmae", "alpha-beta",
                     "kinematic", "poly1", "poly2")


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


def parse_horizons(text: str) -> list[float]:
    """'50ms,100ms' -> seconds, each as :func:`parse_horizon`."""
    return [parse_horizon(part) for part in str(text).split(",") if part.strip()] or [parse_horizon(text)]


def echo_timing(label: str, step: Step, valid: np.ndarray | None = None) -> None:
    """The stream's rate, jitter, repeats and gaps, as the predictors will see them."""
    text = timing_text(label, step, valid)
    if text:
        click.echo(text)


def run_evaluation(path, step: Step, names: list[str], horizons: list[float], plot: str | None,
                   as_json: bool) -> None:
    """Every predictor in ``names`` scored against the recording's own future, per sensor; table, JSON, PNG."""
    from tqdm import tqdm

    from ivc.predict.recording import plot as plot_scores
    from ivc.predict.recording import score, table

    if step.quaternion is None:
        raise click.UsageError("this input has no orientations (signals only): run `ivc correct` first")
    wanted = sorted(set(horizons) | ({round(0.0125 * k, 4) for k in range(1, 1 + int(max(horizons) / 0.0125))}
                                     if plot else set()))
    results = {}
    with tqdm(total=len(names) * step.n_sensors, desc="evaluate", unit="filter", leave=False,
              disable=True if as_json else ON_TERMINAL) as bar:
        for s, sensor in enumerate(step.names):
            predictors = [make(n, step.sample_rate_hz) for n in names]
            results[sensor] = score(predictors, step.quaternion[:, s], step.time, wanted, step.valid_mask[:, s],
                                    progress=bar.update)
    if as_json:
        click.echo(json.dumps({sensor: [{"filter": r.name, "horizons_s": r.horizons_s.tolist(), "rows": r.rows}
                                        for r in scores] for sensor, scores in results.items()}, indent=1))
    else:
        for sensor, scores in results.items():
            picked = [Score(r.name, np.asarray(horizons), [r.at(h) for h in horizons]) for r in scores]
            click.echo(f"sensor {sensor}:\n" + table(picked) + "\n")
        click.echo("median, 95th percentile and RMS of the geodesic angle between each prediction and the "
                   "recording's own orientation at t + horizon (slerp between its samples; frames in the first "
                   "0.5 s, invalid or with a reference across a step over 40 ms left out; no prediction = the "
                   "measured orientation)")
    if plot:
        first = next(iter(results))
        with atomic_figure(plot) as handle:
            plot_scores(results[first], handle, title=f"{Path(path).name}, sensor {first}")
        click.echo(f"wrote {plot}")


def run_compensators(seed: int, evaluations: int, as_json: bool) -> None:
    """Adelstein, Jung & Ellis 2001's designs (default, twist, hybrid) on synthetic 20 s yaw records; Table 1."""
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
                   f"{'noiseless truth' if reference == 'truth' else 'time-shifted measurements'}; Himberg's filters "
                   f"{'tuned on the set above' if tune else 'with the thesis values (Table 3, eq. 67, Table 10)'}\n")
        click.echo(overshoot_table(results) + "\n")
        click.echo(error_table(results) + "\n")
        for m in motions:
            click.echo(horizon_table(results, m) + "\n")
        click.echo(velocity_table(results) + "\n")
        click.echo(snr_table(results))
    if plot:
        with atomic_figure(plot) as handle:
            plot_error_vs_horizon(results, handle)
        click.echo(f"wrote {plot}")


@click.command()
@click.argument("input_file", required=False, type=click.Path(dir_okay=False))
@click.option("--filter", "filters", multiple=True, type=click.Choice(list(FILTERS)),
              help=f"Predictor (default {DEFAULT_FILTER}: the filter that lately predicted each sensor's own stream "
              "best, see docs/predict.md). With --benchmark or --evaluate: repeat to choose several (default: all "
              "but nasa-ekf; --evaluate always adds none and poly1).")
@click.option("--horizon", default="50ms", show_default=True, help="How far ahead, with its unit: 50ms or 0.05s; "
              "with --evaluate a list, 50ms,100ms.")
@click.option("--evaluate", is_flag=True, help="Score the predictors on INPUT_FILE against its own later samples "
              "(slerp) and print median, p95 and RMS error per horizon (--plot: error against horizon as PNG).")
@click.option("--import-unit", type=click.Choice(["m", "cm", "mm", "in"]), default="in", show_default=True,
              help="Position unit of a Polhemus Liberty logger CSV (the file does not say; a Liberty reports inches).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), help="Output: session .h5 or .csv, as the input.")
@click.option("--step", "steps", multiple=True, help="Session input: step(s) to predict (default: all).")
@click.option("--rate", type=RATE_HZ, help="Sample rate (Hz) of a CSV without a usable time column.")
@click.option("--force", is_flag=True, help="Replace OUTPUT (or the --plot file) if it exists (never the input).")
@click.option("--benchmark", is_flag=True, help="Evaluate predictors on synthetic head motion and print the "
              "thesis's tables (horizons 0-117 ms).")
@click.option("--motion", "motions", multiple=True, type=click.Choice(MOTIONS), help="Benchmark motion(s).")
@click.option("--frames", type=int, default=12_000, show_default=True, help="Benchmark frames per motion.")
@click.option("--bench-rate", type=click.Choice(["120", "240"]), default="120", show_default=True)
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--reference", type=click.Choice(["measured", "truth"]), default="measured", show_default=True,
              help="Benchmark reference: time-shifted measurements (the thesis) or the noiseless truth.")
@click.option("--plot", type=click.Path(dir_okay=False), help="--benchmark or --evaluate: write the error-vs-horizon "
              "figure here, in the format of its extension (.png, .svg, .pdf, ...); an existing one only with --force.")
@click.option("--json", "as_json", is_flag=True, help="--benchmark or --evaluate: print the figures as JSON.")
@click.option("--tune", is_flag=True, help="Tune Himberg 2010's filters (q-ekf, dqekf-*, mmdq*) by the thesis's "
              "procedure (measurement noise from the data, process noise at each model's λ) instead of using the "
              "thesis's values: from each input step itself, or with --benchmark from a separate synthetic "
              "tuning set. Prints the estimates.")
@click.option("--tune-from", "tune_from", type=click.Path(exists=True, dir_okay=False),
              help="As --tune, from another recording (.csv) or session (.h5, every step with orientations), "
              "at the input's sample rate: the thesis's separate tuning set.")
@click.option("--compensators", is_flag=True, help="NASA: optimise the 10-state EKF's process noise by Powell's "
              "method for the twist and hybrid costs on synthetic yaw records, and print Table 1.")
@click.option("--evaluations", type=int, default=1500, show_default=True,
              help="With --compensators: cost evaluations per design at most.")
def predict(input_file, filters, horizon, evaluate, import_unit, output, steps, rate, force, benchmark, motions,
            frames, bench_rate, seed, reference, plot, as_json, tune, tune_from, compensators, evaluations):
    """Predict the orientations in INPUT_FILE (session .h5, recording .csv, a head-orientation trace
    `timestamp viewpoint w x y z` or a Polhemus Liberty logger CSV) a horizon ahead.

    The output holds, at each frame's time stamp, the orientation predicted for time +
    horizon from that frame and the ones before it, at the stream's own time steps; positions
    are copied unchanged. Samples the filter cannot predict yet (its first frames) or that are
    invalid keep their measured orientation. `--evaluate` scores the predictors on INPUT_FILE
    against its own later samples. `ivc predict --benchmark` instead evaluates the predictors on
    synthetic head motion and prints the thesis's tables (Tables 5-6, 11, 12-15 layouts, and the
    SNR of Figs. 16-17).
    """
    if plot:
        if not (benchmark or evaluate):
            raise click.UsageError("--plot draws the scores of --evaluate or --benchmark")
        check_plot(plot, force, {"INPUT_FILE": input_file, "--tune-from": tune_from})
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
    if evaluate:
        if input_file is None:
            raise click.UsageError("--evaluate scores the predictors on an INPUT_FILE")
        if output or tune or tune_from:
            raise click.UsageError("--evaluate writes no -o OUTPUT and scores the filters as they are (no --tune)")
        if not Path(input_file).exists():
            raise FileNotFoundError(f"{input_file}: no such recording")
        step = _read_one(input_file, rate, import_unit, steps)
        echo_timing(Path(input_file).name, step)
        names = list(dict.fromkeys(["none", "poly1", *(filters or [f for f in FILTERS if f != "nasa-ekf"])]))
        run_evaluation(input_file, step, names, parse_horizons(horizon), plot, as_json)
        return
    if input_file is None or output is None:
        raise click.UsageError("give INPUT_FILE and -o OUTPUT (or --benchmark)")
    if len(filters) > 1:
        raise click.UsageError("predict a stream with one --filter")
    options = PredictOptions(filter=filters[0] if filters else DEFAULT_FILTER, horizon=parse_horizon(horizon),
                             steps=steps, rate_hz=rate, import_unit=import_unit, tune=tune, tune_from=tune_from,
                             overwrite=force)
    with usage_errors("predict"):
        result = predict_file(input_file, output, options, report=echo_report("predict"))
    click.echo(f"wrote {result.output}")


def _read_one(path, rate, unit, steps) -> Step:
    """The one step to evaluate: a recording, or a session's --step (its only step when there is one)."""
    if session_io.is_recording_csv(path) or sniff(path) is not None:
        step, report = read_recording(path, rate, unit)
        if report is not None:
            click.echo(report.text())
        return step
    data = session_io.read(path)
    names = list(steps) or list(data.steps)
    if len(names) != 1 or names[0] not in data.steps:
        raise click.UsageError(f"--evaluate scores one step: pick it with --step (the session has "
                               f"{', '.join(data.steps) or 'none'})")
    step = data.steps[names[0]]
    if rate:
        step.sample_rate_hz = rate
    return step
