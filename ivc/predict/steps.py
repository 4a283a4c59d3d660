"""Predicting a recorded step's orientations, and tuning the filters from recordings: what ``ivc predict`` and
``ivc correct --predict`` do, as functions that raise :class:`~ivc.errors.PredictorError` and print nothing."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ivc.errors import PredictorError
from ivc.predict import TUNABLE, make
from ivc.predict.timing import StreamTiming, stream_timing
from ivc.predict.tuning import Tuning, estimate
from ivc.session import Step


def tuning_from_steps(steps: Sequence[Step], what: str = "the recording") -> Tuning:
    """A tuning (:mod:`ivc.predict.tuning`) pooled over every step with orientations, all at one sample rate."""
    usable = [s for s in steps if s.quaternion is not None and s.sample_rate_hz]
    if not usable:
        raise PredictorError(f"{what} has no step with orientations and a sample rate to tune from")
    rates = sorted({float(s.sample_rate_hz) for s in usable})
    if len(rates) > 1:
        raise PredictorError(f"{what} has steps at {', '.join(f'{r:g}' for r in rates)} Hz: tune from recordings "
                             "at one rate, the rate of the stream to predict")
    return estimate([s.quaternion for s in usable], rates[0], valid=[s.valid_mask for s in usable])


def tuning_from_file(path: str | Path) -> Tuning:
    """:func:`tuning_from_steps` of every step of a recording (.csv, or another program's format) or session (.h5)."""
    from ivc import session as session_io
    from ivc.collect.imports import read_recording, sniff

    if session_io.is_recording_csv(path) or sniff(path) is not None:
        steps = [read_recording(path)[0]]
    else:
        steps = list(session_io.read(path).steps.values())
    return tuning_from_steps(steps, str(path))


def check_tuning_rate(tuning: Tuning, rate_hz: float, what: str = "the stream") -> None:
    """Refuse a tuning made at another rate than the stream's."""
    if not tuning.matches_rate(rate_hz):
        raise PredictorError(f"the tuning is from a recording at {tuning.rate_hz:g} Hz, {what} is at {rate_hz:g} Hz: "
                             "tune from a recording at the stream's rate")


def step_timing(step: Step, valid: np.ndarray | None = None) -> StreamTiming:
    """The step's rate, jitter, repeats and gaps (:func:`ivc.predict.timing.stream_timing`)."""
    ok = step.valid_mask if valid is None else valid & step.valid_mask
    return stream_timing(step.time, step.quaternion, ok)


def predict_quaternions(step: Step, name: str, horizon: float, valid: np.ndarray | None = None, tune: bool = False,
                        tuning: Tuning | None = None) -> tuple[np.ndarray, Tuning | None]:
    """The step's orientations predicted ``horizon`` s ahead at the step's own time stamps, and the tuning used.

    Samples without a prediction (the filter's first frames, invalid samples) keep the measured orientation.
    ``valid`` narrows the samples used (e.g. the trusted corrections); ``tune``: the filter's measurement and process
    noise are estimated from the step itself (:mod:`ivc.predict.tuning`); or ``tuning`` gives them.
    """
    if step.quaternion is None:
        raise PredictorError("this input has no orientations (signals only): run `ivc correct` first")
    if not step.sample_rate_hz:
        raise PredictorError("the input does not give its sample rate; pass rate_hz=HZ")
    ok = step.valid_mask if valid is None else valid & step.valid_mask
    if tune and name in TUNABLE:
        tuning = estimate(step.quaternion, step.sample_rate_hz, valid=ok)
    elif tuning is not None:
        check_tuning_rate(tuning, step.sample_rate_hz, "the input")
    time = step.time if step.n_frames > 1 and np.all(np.diff(step.time) > 0) else None
    predicted = make(name, step.sample_rate_hz, tuning if name in TUNABLE else None).predict(
        step.quaternion, horizon, ok, time=time)[0]
    return np.where(np.all(np.isfinite(predicted), axis=-1, keepdims=True), predicted, step.quaternion), \
        (tuning if name in TUNABLE else None)


def prediction_attrs(step: Step, name: str, horizon: float, tune: bool, tuning_file: str | None) -> dict:
    """``step``'s attributes with the prediction's: the filter, the horizon (s) and how it was tuned."""
    attrs = dict(step.attrs, predicted_with=name, prediction_horizon_s=horizon,
                 tuned_from_input=bool(tune and name in TUNABLE))
    if tuning_file and name in TUNABLE:
        attrs["tuned_from"] = str(tuning_file)
    return attrs


def predicted_step(step: Step, name: str, horizon: float, tune: bool = False, tuning: Tuning | None = None,
                   tuning_file: str | None = None, valid: np.ndarray | None = None) -> tuple[Step, Tuning | None]:
    """A copy of ``step`` whose orientations are predicted ``horizon`` s ahead (positions and signals as they are)."""
    quaternion, used = predict_quaternions(step, name, horizon, valid, tune, tuning)
    return replace(step, quaternion=quaternion, attrs=prediction_attrs(step, name, horizon, tune, tuning_file)), used
