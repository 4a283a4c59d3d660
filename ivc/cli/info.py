"""``ivc info FILE``: what a session file holds and what it still lacks (or what a look-up table holds)."""

from __future__ import annotations

import json

import click
import h5py
import numpy as np

from ivc import lut
from ivc import session as session_io
from ivc.collect.imports import read_recording, sniff
from ivc.collect.plus import is_plus_sequence, read_plus
from ivc.predict.timing import stream_timing
from ivc.session import STEPS, Session, Step, extension_steps, step_order
from ivc.table import lookup


def summarise_step(step: Step) -> dict:
    """A JSON-ready summary of one step or recording: frames, sensors, rate, duration, valid fraction, data."""
    return {
        "frames": step.n_frames,
        "sensors": step.n_sensors,
        "sample_rate_hz": step.sample_rate_hz,
        "duration_s": float(step.time[-1] - step.time[0]) if step.n_frames > 1 else 0.0,
        "valid_fraction": float(np.mean(step.valid_mask)) if step.n_frames else 0.0,
        "data": "+".join(k for k, v in (("signal", step.signal), ("pose", step.position)) if v is not None),
        **_timing(step),
    }


def _timing(step: Step) -> dict:
    """The time steps as a predictor sees them: rate, median and percentile steps, jitter, repeats, gaps."""
    if step.n_frames < 2 or not np.all(np.diff(step.time) > 0):
        return {}
    timing = stream_timing(step.time, step.quaternion, step.valid_mask)
    return {"measured_rate_hz": timing.rate_hz, "step_ms_p1_median_p99": list(timing.step_ms),
            "jitter_ms": timing.jitter_ms, "repeated_samples": timing.repeats,
            "gaps": [len(g) for g in timing.gaps], "timing": timing.summary()}


def summarise(s: Session) -> dict:
    """A JSON-ready summary of a session: per step frames, sensors, rate, valid fraction."""
    steps = {name: dict(summarise_step(step), truth=name in s.truth) for name, step in s.steps.items()}
    return {
        "hemisphere": s.hemisphere,
        "steps": steps,
        "missing_for_fit": s.missing_for_fit(),
        "has_check": "check" in s.steps,
    }


def render(path: str, summary: dict) -> str:
    lines = [f"{path}: ivc session (format {session_io.FORMAT_VERSION}), hemisphere {summary['hemisphere']}", ""]
    header = f"{'step':<20}{'frames':>9}{'sensors':>9}{'rate Hz':>9}{'seconds':>9}{'valid %':>9}  data"
    lines.append(header)
    lines.append("-" * len(header))
    for name in sorted(set(STEPS) | set(extension_steps(summary["steps"])), key=step_order):
        info = summary["steps"].get(name)
        if info is None:
            lines.append(f"{name:<20}{'—':>9}")
            continue
        truth = "  +truth" if info["truth"] else ""
        lines.append(
            f"{name:<20}{info['frames']:>9}{info['sensors']:>9}{info['sample_rate_hz']:>9.1f}"
            f"{info['duration_s']:>9.2f}{100 * info['valid_fraction']:>9.2f}  {info['data']}{truth}"
        )
    lines.append("")
    if summary["missing_for_fit"]:
        lines.append("Missing before `ivc fit` can run:")
        lines.extend(f"  - {m}" for m in summary["missing_for_fit"])
    else:
        lines.append("Ready for `ivc fit`.")
    if not summary["has_check"]:
        lines.append("No `check` step: `ivc evaluate` needs one (a check file with truth).")
    return "\n".join(lines)


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def info(file: str, as_json: bool) -> None:
    """Summarise a session FILE (steps, frames, sensors, rates, valid fraction, what is missing), a
    look-up table written by `ivc fit` (grid, fit, samples, provenance), or a recording .csv."""
    if _is_table(file):
        from ivc.cli.fit import render_fit

        table = lut.read(file)
        report = {"grid": {"origin_m": table.grid.origin.tolist(), "spacing_m": table.grid.spacing,
                           "shape": list(table.grid.shape)}, "fit": table.fit, "provenance": table.provenance}
        click.echo(json.dumps(report, indent=2) if as_json else f"{file}: ivc look-up table (format "
                   f"{lookup.FORMAT_VERSION}), hemisphere {table.hemisphere}\n" + render_fit(table) +
                   f"\nmade by ivc {table.provenance.get('ivc_version')} on {table.provenance.get('created_utc')}"
                   f" from {table.provenance.get('input', 'an unnamed session')}")
        return
    if session_io.is_recording_csv(file) or sniff(file) is not None or is_plus_sequence(file):
        if is_plus_sequence(file):
            step, report = read_plus(file).step, None
        else:
            step, report = read_recording(file)
        summary = summarise_recording(step)
        if report is not None:
            summary["import_report"] = report.text()
        click.echo(json.dumps(summary, indent=2) if as_json else render_recording(file, summary))
        return
    summary = summarise(session_io.read(file))
    click.echo(json.dumps(summary, indent=2) if as_json else render(file, summary))


def summarise_recording(step: Step) -> dict:
    """:func:`summarise_step` of a recording CSV, with its sensors by name."""
    summary = summarise_step(step)
    if step.sensor_ids is not None:
        summary["sensors"] = [str(s) for s in step.sensor_ids]
    return summary


def render_recording(path: str, summary: dict) -> str:
    sensors = summary["sensors"]
    named = ", ".join(sensors) if isinstance(sensors, list) else str(sensors)
    count = len(sensors) if isinstance(sensors, list) else sensors
    uses = ("`ivc correct LUT FILE -o OUT.csv`, `ivc predict FILE ...`, or `ivc collect STEP --source replay:FILE` "
            "for a session")
    if summary["data"] == "pose":
        uses = "`ivc predict FILE ...`; without signal matrices, `ivc correct` solves from the reported poses"
    if "import_report" in summary:  # a tracker's own log (Liberty logger CSV, head trace): `ivc correct` refuses it
        uses = ("`ivc predict FILE ...`, or `ivc collect STEP --source replay:FILE` to make it a session step, "
                "which `ivc correct` then takes")
    lines = [
        f"{path}: {'PLUS sequence' if is_plus_sequence(path) else 'recording CSV'}, {summary['frames']} frames x "
        f"{count} sensors ({named})",
        f"  {summary['sample_rate_hz']:.1f} Hz, {summary['duration_s']:.2f} s, {100 * summary['valid_fraction']:.2f}% "
        f"valid, data: {summary['data']}",
    ]
    if "import_report" in summary:
        lines[0] = f"{path}: {count} sensors ({named}), imported:"
        lines[1:1] = ["  " + line for line in summary["import_report"].splitlines()[1:]]
    if "timing" in summary:
        lines.extend("  " + line for line in summary["timing"].splitlines())
    lines.append(f"  use it with {uses}")
    return "\n".join(lines)


def _is_table(path: str) -> bool:
    try:
        with h5py.File(path, "r") as h5:
            kind = h5.attrs.get("ivc_format")
    except OSError:
        return False
    return (kind.decode() if isinstance(kind, bytes) else kind) == lookup.FORMAT_NAME
