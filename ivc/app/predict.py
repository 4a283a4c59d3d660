"""Predict a recorded file's orientations ahead: :func:`predict_file`, what ``ivc predict INPUT -o OUTPUT`` does.

The input is a session (.h5), a recording CSV, another program's recording (a head-orientation trace, a Polhemus
Liberty logger CSV: ``ivc.collect.imports``) or a PLUS sequence; the output holds, at each frame's time stamp, the
orientation predicted for time + horizon from that frame and the ones before it (positions unchanged).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from ivc import session as session_io
from ivc.app.correct import plus_output_is_csv, prediction_tuning, timing_text
from ivc.app.inputs import check_rate
from ivc.app.messages import INFO, WARNING, Report, silent
from ivc.app.paths import input_and_output
from ivc.collect.checks import rate_warning
from ivc.collect.imports import read_recording, sniff
from ivc.collect.plus import is_plus_sequence, read_plus, write_plus
from ivc.collect.replay import CsvColumns, read_csv_columns, write_csv
from ivc.errors import OptionsError
from ivc.predict import DEFAULT_FILTER
from ivc.predict import steps as steps_lib
from ivc.predict.tuning import Tuning
from ivc.session import Session, Step

#: the name of the predicted transforms added to a PLUS sequence
PLUS_PREDICTED = "{tool}To{tracker}Predicted"


@dataclass
class PredictOptions:
    """How :func:`predict_file` predicts; every field has the command's default.

    ``filter``: the predictor (``ivc.predict.FILTERS``; default ``auto``, docs/predict.md); ``horizon``: how far
    ahead, in seconds. ``steps``: a session's steps to predict (default: all). ``rate_hz``: the sample rate of a
    recording without a usable time column (Hz); ``import_unit``: the position unit of a Polhemus Liberty logger
    CSV (the file does not say). ``tune``: tune Himberg 2010's filters (q-ekf, dqekf-*, mmdq*) to each step
    itself; ``tune_from``: from this other recording or session instead (``tuning``: a tuning already made from
    it). ``overwrite``: replace the output if it exists (never the input).
    """

    filter: str = DEFAULT_FILTER
    horizon: float = 0.05
    steps: Sequence[str] = ()
    rate_hz: float | None = None
    import_unit: str = "in"
    tune: bool = False
    tune_from: str | os.PathLike | None = None
    tuning: Tuning | None = None
    overwrite: bool = False


@dataclass
class PredictResult:
    """What :func:`predict_file` wrote: ``output``, and ``steps`` {name: the predicted
    :class:`~ivc.session.Step`} (a session's by step name, a recording or PLUS sequence under its file name)."""

    output: Path
    steps: dict[str, Step] = field(default_factory=dict)


def predict_file(input_file: str | os.PathLike, output: str | os.PathLike, options: PredictOptions | None = None,
                 *, report: Report | None = None) -> PredictResult:
    """Predict the orientations in ``input_file`` ``options.horizon`` seconds ahead and write them to ``output``.

    A session is predicted into a session (every step, or ``options.steps``), a recording into a recording CSV, a
    PLUS sequence into the same sequence with ``<Tool>To<Tracker>PredictedTransform`` added (or a CSV, mm).
    Samples the filter cannot predict yet (its first frames) or that are invalid keep their measured orientation.
    ``report(kind, text)`` receives each stream's timing and the tunings (:mod:`ivc.app.messages`).

    >>> from pathlib import Path
    >>> import ivc
    >>> samples = Path(ivc.__file__).parents[1] / "sample_data" / "recordings"   # in the repository
    >>> result = ivc.predict_file(samples / "head_aggressive_120hz.csv", "ahead.csv",
    ...                           ivc.PredictOptions(filter="mmdq2", horizon=0.05))
    >>> ahead = result.steps["head_aggressive_120hz.csv"]
    >>> ahead.quaternion.shape, ahead.attrs["predicted_with"], ahead.attrs["prediction_horizon_s"]
    ((1200, 1, 4), 'mmdq2', 0.05)
    >>> len(ivc.collect.read_csv("ahead.csv").time)       # the output is a recording CSV again
    1200
    """
    options = options or PredictOptions()
    say = report or silent
    check_rate(options.rate_hz)
    input_path, output_path = input_and_output(input_file, output, options.overwrite,
                                               [("tune_from", options.tune_from)])
    tuning = prediction_tuning(options.filter, options.tune, options.tune_from, options.tuning, say)
    job = _Job(options, tuning, say)
    if is_plus_sequence(input_path):
        return job.plus(input_path, output_path)
    if session_io.is_recording_csv(input_path) or sniff(input_path) is not None:
        return job.recording(input_path, output_path)
    return job.session(input_path, output_path)


class _Job:
    """One :func:`predict_file` call: the options, the tuning, and the three input formats."""

    def __init__(self, options: PredictOptions, tuning: Tuning | None, report: Report):
        self.options, self.tuning, self.say = options, tuning, report

    def predicted(self, step: Step) -> Step:
        """The step with its orientations predicted ahead; its signals dropped (they no longer match)."""
        o = self.options
        out, used = steps_lib.predicted_step(step, o.filter, o.horizon, o.tune, self.tuning, o.tune_from)
        if o.tune and used is not None:
            self.say(INFO, used.summary())
        return replace(out, signal=None, description=f"{step.description} (orientation predicted by ivc)".strip())

    def done(self, name: str, step: Step) -> str:
        return (f"{name}: {step.n_frames} frames x {step.n_sensors} sensors predicted {self.options.horizon * 1e3:g} "
                f"ms ahead with {self.options.filter}")

    def plus(self, input_path: Path, output_path: Path) -> PredictResult:
        """A PLUS sequence in; the sequence with ``<Tool>To<Tracker>Predicted`` transforms added (or a CSV, mm)."""
        as_csv = plus_output_is_csv(input_path, output_path, "predicted")
        sequence = read_plus(input_path)
        step = sequence.step
        if self.options.rate_hz:
            step.sample_rate_hz = self.options.rate_hz
        out = self.predicted(step)
        with session_io.atomic_path(output_path) as tmp:
            if as_csv:
                write_csv(out, tmp, length_unit="mm")
            else:
                write_plus(sequence, tmp, {PLUS_PREDICTED: (out.position, out.quaternion, None)})
        self.say(INFO, self.done(input_path.name, step))
        return PredictResult(output_path, {input_path.name: out})

    def recording(self, input_path: Path, output_path: Path) -> PredictResult:
        """A recording CSV, or another program's recording (its import report first), into a recording CSV."""
        o = self.options
        if not session_io.is_recording_csv(output_path):
            raise OptionsError("a recording is predicted into a recording CSV (output=FILE.csv)")
        if sniff(input_path) is not None:  # another program's format: its import report, positions in metres
            step, imported = read_recording(input_path, o.rate_hz, o.import_unit)
            self.say(INFO, imported.text())
            columns = CsvColumns()
        else:
            step, columns = read_csv_columns(input_path, o.rate_hz)
            warning = rate_warning(step) if o.rate_hz is None else None
            if warning:
                self.say(WARNING, warning)
        timing = timing_text(input_path.name, step)
        if timing:
            self.say(INFO, timing)
        out = self.predicted(step)
        with session_io.atomic_path(output_path) as tmp:
            write_csv(out, tmp, columns.extra, length_unit=columns.length_unit)
        self.say(INFO, self.done(input_path.name, step))
        return PredictResult(output_path, {input_path.name: out})

    def session(self, input_path: Path, output_path: Path) -> PredictResult:
        """A session in; a session of the predicted steps out (``predicted_with``, ``prediction_horizon_s``)."""
        o = self.options
        data = session_io.read(input_path)
        names = list(o.steps) or list(data.steps)
        unknown = [n for n in names if n not in data.steps]
        if unknown:
            raise OptionsError(f"{input_path} has no step {', '.join(unknown)} (it has {', '.join(data.steps)})")
        out_steps = {}
        for n in names:
            step = data.steps[n]
            if o.rate_hz and not step.sample_rate_hz:
                step.sample_rate_hz = o.rate_hz
            timing = timing_text(n, step)
            if timing:
                self.say(INFO, timing)
            out_steps[n] = self.predicted(step)
            self.say(INFO, self.done(n, step))
        predicted = Session(data.hemisphere, out_steps, {n: data.truth[n] for n in names if n in data.truth},
                            dict(data.attrs, predicted_with=o.filter, prediction_horizon_s=o.horizon))
        session_io.write(predicted, output_path, overwrite=True)
        return PredictResult(output_path, out_steps)


__all__ = ["PredictOptions", "PredictResult", "predict_file"]
