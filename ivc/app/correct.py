"""Correct a recorded file with a table: :func:`correct_file`, what ``ivc correct`` does, as a call a script makes.

The input is a session file (.h5), a recording CSV (.csv) or a PLUS sequence (.igs.mha, .seq.mha, .igs.nrrd);
the output is written in the input's format (a PLUS sequence may also go to a CSV). Every corrected sample
carries flags (0 trusted; bits of :data:`ivc.session.FLAGS_MEANING`). A live OpenIGTLink stream is corrected by
:class:`ivc.live.LiveCorrector`; :func:`live_corrector` sets one up from the same :class:`CorrectOptions`.

Stage: the app layer sits above ``live``/``export``/``report`` and below ``cli``: it reads the recording formats
of ``collect``, corrects (``correct``), predicts (``predict``) and writes through ``session``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ivc import lut
from ivc import session as session_io
from ivc.app.inputs import check_correct_inputs
from ivc.app.messages import INFO, NOTE, WARNING, Report, silent
from ivc.app.paths import input_and_output
from ivc.collect.checks import rate_warning
from ivc.collect.plus import is_plus_sequence, read_plus, write_plus
from ivc.collect.replay import read_csv_columns, write_csv
from ivc.collect.tracker_units import apply_tracker_file
from ivc.correct import Correction, Corrector, PoseCorrector, describe
from ivc.correct.flags import HIGH_RESIDUAL, INVALID_INPUT, LOW_PRECISION, NOT_CONVERGED, OUTSIDE
from ivc.correct.precision import DEFAULT
from ivc.correct.residual_gate import RESIDUAL_SIGMAS
from ivc.correct.rigid import agree_with_body, decide_with_body
from ivc.errors import OptionsError
from ivc.fixtures.wand import WandCalibration
from ivc.lut.build import file_digest
from ivc.predict import TUNABLE
from ivc.predict.steps import predicted_step, step_timing, tuning_from_file
from ivc.predict.tuning import Tuning
from ivc.session import Session, Step, StepCorrection, extension_steps

#: the name of the corrected transforms added to a PLUS sequence
PLUS_CORRECTED = "{tool}To{tracker}Ivc"
#: free-space steps: nothing to correct there
FREE_SPACE_STEPS = ("cube_calibration", "wand_calibration")


@dataclass
class CorrectOptions:
    """How :func:`correct_file` (and :func:`live_corrector`) correct; every field has the command's default.

    ``steps``: a session's steps to correct (default: every step recorded in the distorted volume).
    ``interpolation``: the table's interpolation (``ivc.table.grid.INTERPOLATIONS``). ``max_residual``: flag (4)
    corrections whose rms(M − T S)/rms(S) exceeds it (default None: a limit per pose scaled to the table's
    cross-validated model error and the signal noise, ``ivc.correct.residual_gate``). ``hemisphere``: of a CSV
    or PLUS input (default: the table's). ``solver``: the tracker's own pose solver, for inputs of reported poses
    only (``closed-form`` or ``least-squares``; default: the one the table was fitted for, else closed-form).

    ``precision``: predict each pose's RMS position (m) and orientation (rad) error from the tracker's signal noise
    (on by default wherever the noise is known, for signals and reported poses alike; docs/trust.md).
    ``max_precision`` (m): flag (16) poses predicted less precise than this (default
    :data:`ivc.correct.precision.MAX_PRECISION`, 1 mm; None: no gate). ``signal_noise``: the tracker's white noise
    per signal entry, in signal units (default: what the table's fit measured). ``tracker_model``: a tracker file
    (``ivc tracker calibrate``) that brings the input's signals to ideal-dipole units first.

    ``predictor``: then predict each sensor's corrected orientation ``horizon`` s ahead with this filter
    (``ivc.predict.FILTERS``) from the trusted samples; ``tune``: tune Himberg's filters to each corrected step's
    trusted samples; ``tune_from``: tune them from this recording or session instead (``tuning``: a tuning already
    made from it). ``overwrite``: replace the output if it exists (never an input). ``allow_corrected``: take an
    input that is ivc's corrected output (refused otherwise: its poses would be corrected twice).

    ``rigid_body``: the recording's sensors are fixed to one body of this geometry (a
    :class:`~ivc.fixtures.wand.WandCalibration`, or a file :func:`load_rigid_body` reads); a trusted sensor the
    body's other trusted sensors do not agree with is flagged (4) (:func:`ivc.correct.rigid.agree_with_body`), and a
    reported pose the map produces twice is trusted where the body puts it on one branch
    (:func:`ivc.correct.rigid.decide_with_body`). In a session it applies to the wand's steps (its sweep and
    extension sweeps); in a CSV or PLUS recording to every sensor, which must be the body's, in its order.
    """

    steps: Sequence[str] = ()
    interpolation: str = "cubic"
    max_residual: float | None = None
    hemisphere: str | None = None
    solver: str | None = None
    precision: bool = True
    max_precision: float | str | None = DEFAULT
    signal_noise: float | None = None
    tracker_model: str | os.PathLike | None = None
    predictor: str | None = None
    horizon: float = 0.05
    tune: bool = False
    tune_from: str | os.PathLike | None = None
    tuning: Tuning | None = None
    overwrite: bool = False
    allow_corrected: bool = False
    rigid_body: str | os.PathLike | WandCalibration | None = None

    def precision_keywords(self) -> dict:
        """The correctors' precision keywords (:class:`~ivc.correct.Corrector`, :class:`~ivc.correct.PoseCorrector`)."""
        return {"precision": self.precision, "signal_noise": self.signal_noise, "max_precision": self.max_precision}

    def check(self) -> None:
        """Refuse options that do not go together (:class:`~ivc.errors.OptionsError`)."""
        if (self.tune or self.tune_from) and not self.predictor:
            raise OptionsError("tune=True and tune_from=FILE tune a prediction filter: give predictor=NAME too")


@dataclass
class CorrectResult:
    """What :func:`correct_file` wrote.

    ``output``: the file; ``corrections``: {name: :class:`~ivc.correct.Correction`}, a session's steps by step
    name, a CSV or PLUS input under its file name; ``steps``: {name: the :class:`~ivc.session.Step` written}
    (corrected poses, and predicted orientations with ``predictor``); ``advice``: {name: what to check} for the
    steps where most valid samples were flagged.
    """

    output: Path
    corrections: dict[str, Correction] = field(default_factory=dict)
    steps: dict[str, Step] = field(default_factory=dict)
    advice: dict[str, str] = field(default_factory=dict)

    @property
    def trusted(self) -> int:
        """How many samples were corrected and trusted (flags 0), over every step."""
        return int(sum(np.sum(out.flags == 0) for out in self.corrections.values()))


def correct_file(lut_file: str | os.PathLike, input_file: str | os.PathLike, output: str | os.PathLike,
                 options: CorrectOptions | None = None, *, report: Report | None = None) -> CorrectResult:
    """Correct the poses in ``input_file`` with the table ``lut_file`` and write them to ``output``.

    ``input_file``: a session (.h5; every step recorded in the distorted volume, or ``options.steps``), a recording
    CSV (.csv; corrected into a CSV, the input's extra columns kept) or a PLUS sequence (.igs.mha, .seq.mha,
    .igs.nrrd; written back with ``<Tool>To<Tracker>IvcTransform`` and its flags added, or into a CSV in mm).
    Signals are used when the input has them; otherwise the reported poses are corrected by inverting the tracker's
    pose-domain distortion (docs/lut.md). ``report(kind, text)`` receives each step's summary and what to check
    as it goes (:mod:`ivc.app.messages`). The output is written atomically; an existing one is replaced only with
    ``options.overwrite``, an input never.

    Raises :class:`~ivc.errors.OptionsError` for options that do not fit together or do not fit the input, and the
    readers' errors (:class:`~ivc.errors.SessionError`, :class:`~ivc.errors.LutError`) for a malformed file.

    >>> from pathlib import Path
    >>> import ivc
    >>> samples = Path(ivc.__file__).parents[1] / "sample_data" / "recordings"   # in the repository
    >>> result = ivc.correct_file(samples / "default_room_lut.h5", samples / "default_room_check.csv",
    ...                           "corrected.csv", ivc.CorrectOptions(max_precision=0.5e-3))
    >>> flags = result.corrections["default_room_check.csv"].flags   # 240 frames of one sensor
    >>> flags.shape, result.trusted, int((flags == ivc.correct.LOW_PRECISION).sum())  # 5 less precise than 0.5 mm
    ((240, 1), 235, 5)
    >>> result.output.read_text().splitlines()[0].split(",")[-4:]   # ivc's columns after the input's
    ['flags', 'residual', 'precision_mm', 'orientation_precision_mrad']
    """
    options = options or CorrectOptions()
    check_correct_inputs(lut_file, input_file, options.allow_corrected)
    say = report or silent
    options.check()
    input_path, output_path = input_and_output(input_file, output, options.overwrite,
                                               [("lut_file", lut_file), ("tune_from", options.tune_from)])
    tuning = prediction_tuning(options.predictor, options.tune, options.tune_from, options.tuning, say)
    table = lut.read(lut_file)
    job = _Job(table, lut_file, options, tuning, say)
    if is_plus_sequence(input_path):
        return job.plus(input_path, output_path)
    if session_io.is_recording_csv(input_path):
        return job.csv(input_path, output_path)
    return job.session(input_path, output_path)


def prediction_tuning(name: str | None, tune: bool, tune_from: str | os.PathLike | None, tuning: Tuning | None,
                      report: Report = silent) -> Tuning | None:
    """The tuning of ``tune_from`` (``tune`` tunes later, per step), or ``tuning`` when it is already made.

    Filters without a noise model to tune are predicted as they are, with a note that says so."""
    if not name:
        return None
    if tune and tune_from:
        raise OptionsError("give tune=True (from the input) or tune_from=FILE, not both")
    if (tune or tune_from) and name not in TUNABLE:
        report(NOTE, f"{name} has no noise model to tune (only {', '.join(TUNABLE)} have): predicting without "
               "tuning")
        return None
    if tuning is None and tune_from:
        tuning = tuning_from_file(tune_from)
        report(INFO, f"tune_from={tune_from}:\n" + tuning.summary())
    return tuning


def plus_output_is_csv(input_path: Path, output_path: Path, what: str) -> bool:
    """Whether a PLUS sequence's output is a CSV; refused unless it is that or a sequence of the input's format."""
    as_csv = session_io.is_recording_csv(output_path)
    if not (output_path.suffix.lower() == input_path.suffix.lower() or as_csv):
        raise OptionsError(f"a PLUS sequence is {what} into a sequence of the same format (output=FILE"
                           f"{input_path.suffix}) or a CSV (output=FILE.csv)")
    return as_csv


def timing_text(label: str, step: Step, valid: np.ndarray | None = None) -> str | None:
    """The stream's rate, jitter, repeats and gaps as the predictors will see them (None: no orientations)."""
    if step.quaternion is None or step.n_frames < 2:
        return None
    if not np.all(np.diff(step.time) > 0):
        return f"{label}: the time stamps do not increase; frames are taken 1 / {step.sample_rate_hz:g} Hz apart"
    return f"{label}: " + step_timing(step, valid).summary().replace("\n", "\n  ")


def corrected_step(step: Step, out: Correction, lut_file: str | os.PathLike) -> Step:
    """The step with its reported poses replaced by the corrected ones (signals kept as measured); a sample
    without a corrected pose (flagged: invalid input, not converged) is written as not valid."""
    attrs = dict(step.attrs, corrected_with=str(lut_file))
    posed = np.all(np.isfinite(out.position), axis=-1) & np.all(np.isfinite(out.quaternion), axis=-1)
    return Step(step.time, step.signal, out.position, out.quaternion, step.valid_mask & posed, step.sample_rate_hz,
                step.sensor_ids, f"{step.description} (corrected by ivc)".strip(), attrs)


def step_correction(out: Correction) -> StepCorrection:
    """The datasets a corrected session stores for a step's correction (:class:`ivc.session.StepCorrection`)."""
    return StepCorrection(out.flags, out.residual, out.precision, out.orientation_precision)


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


def summary(name: str, out: Correction) -> str:
    """One line on a step's correction: samples, trusted, each flag combination, the predicted precision."""
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


def correction_advice(out: Correction, max_residual: float | None, pose_only: bool = False) -> str | None:
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
    if bit == OUTSIDE and np.mean((flags[valid] & (OUTSIDE | HIGH_RESIDUAL)) == (OUTSIDE | HIGH_RESIDUAL)) >= 0.5:
        return (f"{percent} lie outside the table's mapped volume and do not fit its field either: check the "
                "signals' scale and units (the table's session's, e.g. not x1000), the hemisphere (hemisphere=AXIS), "
                "and that this was recorded with the same source, before sweeping more of the room")
    if bit == OUTSIDE:
        return (f"{percent} lie outside the table's mapped volume: sweep the wand there and fit again "
                "(`ivc report` shows the coverage)")
    if bit == HIGH_RESIDUAL and pose_only:
        return (f"{percent} are reported poses the table's map does not produce (or not uniquely): was this "
                "recorded in the mapped room, with the source where it was when the table was fitted, in the "
                "table's hemisphere, and with the tracker solver the table assumes (solver=NAME)?")
    if bit == HIGH_RESIDUAL:
        median = float(np.median(out.residual.reshape(-1)[valid]))
        gate = (f"gate max_residual={max_residual:g}" if max_residual is not None else
                f"gate {RESIDUAL_SIGMAS:g}x what the table's model error and the signal noise explain; "
                "max_residual=LIMIT sets one fixed limit")
        return (f"{percent} do not fit the table's field (median residual {median:.2g}, {gate}): was this "
                "recorded in the mapped room, with the source where it was when the table was fitted, and in the "
                "table's hemisphere?")
    if bit == LOW_PRECISION:
        return (f"{percent} are predicted less precise than the precision limit (max_precision): the tracker's noise "
                "allows no better there (far from the source, or where the room's field folds the map); loosen the "
                "limit, or average frames of a static sensor")
    return (f"{percent} did not converge: check the hemisphere (hemisphere=AXIS for a CSV) and that the signals "
            "are in the tracker's units")


def load_rigid_body(source: str | os.PathLike | WandCalibration, hemisphere: str = "+x") -> WandCalibration:
    """A rigid body's geometry: a :class:`~ivc.fixtures.wand.WandCalibration` as given; a session (``.h5``) whose
    ``wand_calibration`` step holds the body's sensors in free space (ivc's own wand calibration); or a JSON
    file ``{"positions": [[x, y, z], ...], "quaternions": [[w, x, y, z], ...]}``, each sensor's pose in one body
    frame (metres), in the order of the recording's sensors."""
    if isinstance(source, WandCalibration):
        return source
    path = Path(source)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
            position, quaternion = np.asarray(data["positions"], float), np.asarray(data["quaternions"], float)
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise OptionsError(f"{path}: not a rigid body ({error}); give {{\"positions\": [[x, y, z], ...], "
                               f"\"quaternions\": [[w, x, y, z], ...]}} in metres, one per sensor") from None
        return WandCalibration.from_poses(position, quaternion)
    data = session_io.read(path)
    if "wand_calibration" not in data.steps:
        raise OptionsError(f"{path} has no wand_calibration step to take a rigid body's geometry from (it has "
                           f"{', '.join(data.steps)}); give a JSON file of the sensors' poses instead")
    return WandCalibration.from_step(data.steps["wand_calibration"], data.hemisphere or hemisphere)


class _Job:
    """One :func:`correct_file` call: the table and options, and the three input formats."""

    def __init__(self, table, lut_file, options: CorrectOptions, tuning: Tuning | None, report: Report):
        self.table, self.lut_file, self.options, self.tuning, self.say = table, lut_file, options, tuning, report
        self.precision = options.precision_keywords()
        self._gate_said = False
        self.body = None if options.rigid_body is None else load_rigid_body(options.rigid_body, table.hemisphere)

    def correct(self, step: Step, hemisphere: str, rigid: bool = True) -> Correction:
        """A step's corrections: from its signals when it has them, else from its reported poses, as the time
        series they are (:meth:`~ivc.correct.PoseCorrector.track`: a continuing track keeps its branch); then,
        where ``rigid`` and a rigid body is given, the sensors its other sensors do not agree with flagged."""
        o = self.options
        if step.signal is not None:
            corrector = Corrector(self.table, hemisphere, o.interpolation, o.max_residual, **self.precision)
            if not self._gate_said:
                self.say(INFO, corrector.residual_gate.describe())
            self._gate(corrector.gate)
            out = corrector.batch(step.signal, step.valid_mask)
        else:
            poses = PoseCorrector(self.table, hemisphere, o.interpolation, o.solver, **self.precision)
            self._gate(poses.gate)
            out = poses.track(step.position, step.quaternion, step.valid_mask)
        if rigid and self.body is not None:
            flagged = agree_with_body(out, self.body)
            self.say(INFO, f"{step.description or 'step'}: {int(flagged.sum())} trusted samples flagged (4): their "
                           f"rigid body's other sensors disagree, or too few agree")
            if step.signal is None:
                decided = decide_with_body(poses, step.position, step.quaternion, out, self.body)
                self.say(INFO, f"{step.description or 'step'}: {int(decided.sum())} samples the reported pose left "
                               f"ambiguous trusted: their rigid body puts them on one branch")
        return out

    def _gate(self, gate) -> None:
        """Say once how the precision is gated (the default limit, another, none, or why not predicted)."""
        if not self._gate_said:
            self._gate_said = True
            self.say(NOTE if gate.note else INFO, gate.describe())

    def finish(self, name: str, step: Step, out: Correction, result: CorrectResult) -> None:
        """Report a step's summary and advice, and keep its correction in ``result``."""
        result.corrections[name] = out
        self.say(INFO, summary(name, out))
        advice = correction_advice(out, self.options.max_residual, step.signal is None)
        if advice:
            result.advice[name] = advice
            self.say(WARNING, advice)

    def predicted(self, step: Step, out: Correction) -> Step:
        """Corrected orientations predicted ``horizon`` s ahead from the trusted (unflagged) samples."""
        o = self.options
        timing = timing_text(f"{step.description or 'step'} (trusted samples)", step, out.ok)
        if timing:
            self.say(INFO, timing)
        predicted, used = predicted_step(step, o.predictor, o.horizon, o.tune, self.tuning, o.tune_from,
                                         valid=out.ok)
        if o.tune and used is not None:
            self.say(INFO, used.summary())
        return predicted

    def plus(self, input_path: Path, output_path: Path) -> CorrectResult:
        """A PLUS sequence in; the sequence with ``<Tool>To<Tracker>Ivc`` transforms added out (or a CSV, mm).

        A sequence holds reported poses only, so they are corrected through the pose path (the inverse of the
        tracker's pose-domain distortion), not from signals rebuilt from them."""
        o = self.options
        if o.tracker_model is not None:
            raise OptionsError("tracker_model=FILE applies to signal matrices; a PLUS sequence holds poses only")
        as_csv = plus_output_is_csv(input_path, output_path, "corrected")
        sequence = read_plus(input_path)
        step = sequence.step
        self._warn(rate_warning(step))
        out = self.correct(step, o.hemisphere or self.table.hemisphere)
        fixed = corrected_step(step, out, self.lut_file)
        fixed.valid = out.flags == 0
        if o.predictor:
            fixed = self.predicted(fixed, out)
        with session_io.atomic_path(output_path) as tmp:
            if as_csv:
                write_csv(fixed, tmp, {"flags": out.flags, "residual": out.residual, **precision_columns(out)},
                          length_unit="mm")
            else:
                extra = {} if out.precision is None else {"PrecisionMm": 1000 * out.precision}
                write_plus(sequence, tmp, {PLUS_CORRECTED: (fixed.position, fixed.quaternion, out.flags, extra)})
        result = CorrectResult(output_path, steps={input_path.name: fixed})
        self.finish(input_path.name, step, out, result)
        if sequence.other_transforms:
            self._warn(f"not corrected (not to the {sequence.tracker} frame): {', '.join(sequence.other_transforms)}")
        return result

    def csv(self, input_path: Path, output_path: Path) -> CorrectResult:
        """A recording CSV in; the corrected CSV out, in the input's length unit, its extra columns kept."""
        o = self.options
        if not session_io.is_recording_csv(output_path):
            raise OptionsError("a CSV input is corrected into a CSV output (output=FILE.csv)")
        step, columns = read_csv_columns(input_path)
        self._warn(rate_warning(step))
        hemisphere = o.hemisphere or self.table.hemisphere
        if o.tracker_model is not None:
            step = apply_tracker_file(Session(hemisphere, {"recording": step}), o.tracker_model).steps["recording"]
        out = self.correct(step, hemisphere)
        fixed = corrected_step(step, out, self.lut_file)
        fixed.signal = None
        fixed.valid = out.flags == 0  # valid: the corrected pose is trusted (flags say why not)
        if o.predictor:
            fixed = self.predicted(fixed, out)
        extra, renamed = csv_output_columns(columns.extra, {"flags": out.flags, "residual": out.residual,
                                                            **precision_columns(out)})
        for old, new in renamed.items():
            self._warn(f"the input's column {old!r} is written as {new!r} (ivc writes its own {old!r})")
        with session_io.atomic_path(output_path) as tmp:
            write_csv(fixed, tmp, extra, length_unit=columns.length_unit)
        result = CorrectResult(output_path, steps={input_path.name: fixed})
        self.finish(input_path.name, step, out, result)
        return result

    def session(self, input_path: Path, output_path: Path) -> CorrectResult:
        """A session in; a session of the corrected steps out, with their flags, residuals and precision."""
        o = self.options
        data = session_io.read(input_path)
        names = list(o.steps) or [n for n in data.steps if n not in FREE_SPACE_STEPS]
        unknown = [n for n in names if n not in data.steps]
        if unknown:
            raise OptionsError(f"{input_path} has no step {', '.join(unknown)} (it has {', '.join(data.steps)})")
        data = apply_tracker_file(data, o.tracker_model, names)
        result = CorrectResult(output_path)
        wand_steps = {"wand_sweep", *extension_steps(data.steps)}  # the steps whose sensors are the wand's
        for name in names:
            out = self.correct(data.steps[name], data.hemisphere, rigid=name in wand_steps)
            self.finish(name, data.steps[name], out, result)
        fixed = {n: corrected_step(data.steps[n], result.corrections[n], self.lut_file) for n in names}
        if o.predictor:
            fixed = {n: self.predicted(fixed[n], result.corrections[n]) for n in names}
        corrected = Session(data.hemisphere, fixed, {n: data.truth[n] for n in names if n in data.truth},
                            dict(data.attrs, corrected_with=str(self.lut_file), lut_sha256=file_digest(self.lut_file)))
        session_io.write(corrected, output_path, overwrite=True,
                         corrections={n: step_correction(out) for n, out in result.corrections.items()})
        result.steps = fixed
        return result

    def _warn(self, advice: str | None) -> None:
        if advice:
            self.say(WARNING, advice)


@dataclass
class LiveOptions:
    """Where :func:`live_corrector` serves and how it reads the stream.

    ``publish``: (host, port) the corrected poses are served on (port 0: any free port); ``length_unit``: of the
    stream's translations (``ivc.units.LENGTH_UNITS``; PLUS and Slicer use mm); ``sensors``: correct only these
    device names (default: every device that sends TRANSFORM or NDARRAY messages); ``rate_hz``: the stream's sample
    rate, for the prediction. With ``CorrectOptions.rigid_body``, ``sensors`` names the body's sensors in its order,
    and each round's trusted sensors the others disagree with are flagged (4).
    """

    publish: tuple[str, int] = ("127.0.0.1", 18945)
    length_unit: str = "mm"
    sensors: Sequence[str] = ()
    rate_hz: float = 240.0


def live_corrector(lut_file: str | os.PathLike, url: str, options: CorrectOptions | None = None,
                   live: LiveOptions | None = None, *, report: Report | None = None):
    """An :class:`ivc.live.LiveCorrector` for the OpenIGTLink server at ``url`` (``igtl://HOST:PORT``) with the
    table ``lut_file`` and the correction of ``options``; start it with its ``run(duration)`` (docs/live.md).

    Poses (TRANSFORM) are corrected through the pose path with ``options.solver``; signal matrices (NDARRAY 3x3)
    through the field, flagged (16) over ``options.max_precision``. ``options.tune`` is refused (it needs the
    whole recording): tune from an earlier one with ``options.tune_from``."""
    from ivc.live import LiveCorrector, parse_url
    from ivc.units import LENGTH_UNITS

    options = options or CorrectOptions()
    live = live or LiveOptions()
    options.check()
    if options.tracker_model is not None:
        raise OptionsError("tracker_model=FILE applies to recorded signals; a live stream must be in ideal units")
    if options.tune:
        raise OptionsError("tune=True needs the whole recording and cannot run on a live stream: tune from an "
                           "earlier recording with tune_from=FILE")
    tuning = prediction_tuning(options.predictor, options.tune, options.tune_from, options.tuning,
                               report or silent)
    if tuning is not None and not tuning.matches_rate(live.rate_hz):
        raise OptionsError(f"tune_from=FILE is a recording at {tuning.rate_hz:g} Hz, the live stream (rate_hz="
                           f"{live.rate_hz:g}) is at {live.rate_hz:g} Hz: tune from a recording at the stream's rate")
    if live.length_unit not in LENGTH_UNITS:
        raise OptionsError(f"length_unit={live.length_unit!r}: use one of {', '.join(LENGTH_UNITS)}")
    table = lut.read(lut_file)
    hemisphere = options.hemisphere or table.hemisphere
    corrector = Corrector(table, hemisphere, options.interpolation, options.max_residual,
                          **options.precision_keywords())
    poses = PoseCorrector(table, hemisphere, options.interpolation, options.solver, **options.precision_keywords())
    body = None if options.rigid_body is None else load_rigid_body(options.rigid_body, hemisphere)
    return LiveCorrector(corrector, parse_url(url), tuple(live.publish), length_unit=LENGTH_UNITS[live.length_unit],
                         predictor=options.predictor, horizon=options.horizon if options.predictor else 0.0,
                         rate_hz=live.rate_hz, tuning=tuning, pose_corrector=poses, sensors=list(live.sensors) or None,
                         rigid_body=body)


__all__ = ["CorrectOptions", "CorrectResult", "LiveOptions", "correct_file", "live_corrector"]
