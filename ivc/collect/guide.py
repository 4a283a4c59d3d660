"""Guided collection: record protocol steps from a live source until each step's stop rule is met.

:func:`collect_step` reads an open :class:`~ivc.collect.stream.LiveSource`, keeps every frame as recorded
(:class:`~ivc.collect.stream.StepRecorder`), watches each sensor (OK / missing / stale, rate, jitter) and the
step's stop rule (:mod:`ivc.collect.rules`), and reports a :class:`StepStatus` to ``on_status`` as it goes. It
returns the :class:`~ivc.session.Step` (or None when what was recorded cannot be kept) and a :class:`StepReport`
saying in words how the step ended. :func:`collect_protocol` walks the protocol's steps in order, writing each
kept step to the session file through :func:`ivc.session.add_step` (atomic: never a half-written file).

A rehearsal source whose samples carry step labels (:attr:`Sample.step`: a replayed session, ``ivc serve sim``)
is followed: a step records exactly the frames labelled with it, and ends where the source moves on to a later
step (the stop rule is still shown). A stop request (``stop``, a :class:`threading.Event`, or Ctrl-C) ends a step
cleanly: what was recorded is kept when the rule says it makes a valid step, else dropped, and the report says
which. Times are on the source's clock; the host clock only paces status reports and measures jitter.
"""

from __future__ import annotations

import threading
import time as _time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ivc import rotations
from ivc.collect.rules import Frames, Progress, StopRule, default_rule
from ivc.collect.stream import Sample, SourceEvent, StaleWatch, StepRecorder
from ivc.errors import InputError, IvcError
from ivc.session import (
    CUBE_SENSORS,
    STEPS,
    Session,
    Step,
    add_step,
    describe_step,
    is_known_step,
    step_order,
    write,
)

#: a sensor is stale (repeats its pose exactly) or missing (no valid pose) after this long, source clock (s)
STALE_AFTER_S = 0.5
#: a rehearsal's step ends when nothing more arrives for this long after its labelled frames (host clock, s)
REHEARSAL_IDLE_S = 3.0
#: rate and jitter are measured over this many recent frames
WINDOW_FRAMES = 480
#: what to tell the person before each step
INSTRUCTIONS = {
    "cube_calibration": "Put the interpolation cube in free space (no metal within a metre) and leave it still.",
    "cube_survey": "Put the cube at its declared pose in the room and leave it still.",
    "wand_calibration": "Put the mapping wand in free space and leave it still.",
    "wand_sweep": "Hold the wand's tip (sensor 0) inside the cube and sweep its far end slowly through every "
                  "direction.",
    "check": "Move the check sensor through the working volume, in any orientation.",
}
EXTENSION_INSTRUCTION = ("Walk the wand through the working volume, its tip pointing back toward the cube, part of "
                         "it inside the region mapped so far.")

SensorWord = Literal["OK", "missing", "stale"]
Outcome = Literal["done", "kept", "dropped"]


def instruction(step: str) -> str:
    """What the person does during ``step``, in one or two sentences."""
    return INSTRUCTIONS.get(step, EXTENSION_INSTRUCTION)


@dataclass(frozen=True)
class SensorState:
    """One sensor's state: ``state`` OK / missing (no valid pose for :data:`STALE_AFTER_S`) / stale (its pose
    repeats exactly); ``rate_hz`` of valid frames and ``jitter_ms`` (standard deviation of the intervals between
    them, source clock) over the recent window."""

    name: str
    state: SensorWord
    rate_hz: float
    jitter_ms: float
    since_s: float = 0.0  # how long it has been missing or stale (s)


@dataclass
class StepStatus:
    """A snapshot of a step being collected, for a terminal or a 3D view.

    ``rule`` states the stop rule; ``progress`` its numbers; ``problems`` in plain words; ``thin`` the region
    still short; ``target`` (3,) m a point to go to next; ``points`` (M, 3) m sample positions so far (a bounded
    subsample); ``latest`` (N, 3) m the last frame's sensor positions (NaN where invalid); ``cube`` (8, 3) m the
    cube's vertices when known. ``frames`` recorded (after any restart), ``elapsed_s`` of tracker time."""

    step: str
    instruction: str
    rule: str
    frames: int
    elapsed_s: float
    sensors: list[SensorState]
    progress: list[Progress]
    problems: list[str]
    done: bool
    thin: str | None = None
    target: NDArray[np.float64] | None = None
    points: NDArray[np.float64] | None = None
    latest: NDArray[np.float64] | None = None
    cube: NDArray[np.float64] | None = None
    restarts: int = 0
    cells: list = field(default_factory=list)  # coverage regions: (centre (3,) m, share 0-1 of their target)


@dataclass
class StepReport:
    """How a step ended. ``outcome``: ``done`` (the stop rule was met, or a rehearsal source's step ended),
    ``kept`` (stopped early, but what was recorded makes a valid step) or ``dropped`` (nothing kept);
    ``message`` says so in words; ``stopped`` is True when a stop request or Ctrl-C ended it."""

    step: str
    outcome: Outcome
    message: str
    frames: int
    rule: str
    progress: list[Progress]
    problems: list[str] = field(default_factory=list)
    events: list[SourceEvent] = field(default_factory=list)
    restarts: int = 0
    dropped_frames: int = 0
    stopped: bool = False

    @property
    def kept(self) -> bool:
        return self.outcome != "dropped"


class SourceFeed:
    """An open live source with a push-back buffer: the frames of the next step, read while finishing this one,
    wait here for it. ``finished`` when the buffer is empty and the source says it has nothing more (a
    rehearsal source's ``finished``; a live tracker never finishes)."""

    def __init__(self, source):
        self.source = source
        self._pending: list[Sample | SourceEvent] = []

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(getattr(self.source, "sensor_names", ()) or ())

    @property
    def sample_rate_hz(self) -> float | None:
        return getattr(self.source, "sample_rate_hz", None)

    def read(self, timeout_s: float) -> list[Sample | SourceEvent]:
        if self._pending:
            out, self._pending = self._pending, []
            return out
        return self.source.read(timeout_s)

    def push_back(self, items: Sequence[Sample | SourceEvent]) -> None:
        self._pending = list(items) + self._pending

    @property
    def finished(self) -> bool:
        return not self._pending and bool(getattr(self.source, "finished", False))


class SensorMonitor:
    """Per-sensor state from the samples as they arrive: stale (via :class:`StaleWatch`), missing, rate and
    jitter over the last :data:`WINDOW_FRAMES` frames (source clock)."""

    def __init__(self, names: Sequence[str], after_s: float = STALE_AFTER_S):
        self.names = list(names)
        n = len(self.names)
        self.after_s = after_s
        self.watch = StaleWatch(n, after_s, self.names)
        self.last_valid = np.full(n, np.nan)
        self.stale_since = np.full(n, np.nan)
        self.start: float | None = None
        self.now = 0.0
        self.host_last: float | None = None
        self._times: deque[float] = deque(maxlen=WINDOW_FRAMES)
        self._valid: deque[NDArray[np.bool_]] = deque(maxlen=WINDOW_FRAMES)

    def update(self, sample: Sample) -> list[SourceEvent]:
        if self.start is None:
            self.start = float(sample.time)
            self.last_valid[:] = sample.time
        self.now = float(sample.time)
        valid = np.asarray(sample.valid, bool)
        self.last_valid[valid] = sample.time
        self._times.append(self.now)
        self._valid.append(valid)
        if sample.host_time is not None:
            self.host_last = sample.host_time
        events = self.watch.update(sample)
        for event in events:
            if event.kind == "stale":
                self.stale_since[event.sensor] = self.now - self.after_s
            elif event.kind == "resumed":
                self.stale_since[event.sensor] = np.nan
        return events

    def states(self) -> list[SensorState]:
        times = np.asarray(self._times)
        valid = np.asarray(self._valid) if self._valid else np.zeros((0, len(self.names)), bool)
        missing_for = self.now - self.last_valid
        stale = self.watch.stale
        out = []
        for k, name in enumerate(self.names):
            t = times[valid[:, k]] if len(times) else times
            span = float(times[-1] - times[0]) if len(times) > 1 else 0.0
            rate = (len(t) - 1) / span if span > 0 and len(t) > 1 else 0.0
            jitter = 1e3 * float(np.std(np.diff(t))) if len(t) > 2 else 0.0
            if missing_for[k] >= self.after_s:
                out.append(SensorState(name, "missing", rate, jitter, float(missing_for[k])))
            elif stale[k]:
                out.append(SensorState(name, "stale", rate, jitter, float(self.now - self.stale_since[k])))
            else:
                out.append(SensorState(name, "OK", rate, jitter))
        return out


def _problem_words(states: list[SensorState]) -> list[str]:
    return [f"sensor {k} ({s.name}) {s.state} for {s.since_s:.1f} s" if s.name != str(k) else
            f"sensor {k} {s.state} for {s.since_s:.1f} s" for k, s in enumerate(states) if s.state != "OK"]


def frames_of(samples: Sequence[Sample], hemisphere: str) -> Frames:
    """A batch of samples as the rules read them: the reported poses, or the closed-form dipole pose of the
    signals when a source sends no pose (NaN where a sample is invalid)."""
    time = np.array([s.time for s in samples], float)
    valid = np.stack([np.asarray(s.valid, bool) for s in samples])
    signal = np.stack([s.signal for s in samples]).astype(float) if samples[0].signal is not None else None
    if samples[0].position is not None:
        position = np.stack([s.position for s in samples]).astype(float)
        quaternion = np.stack([s.quaternion for s in samples]).astype(float)
    else:
        position, quaternion = Step(time=time, signal=signal, valid=valid).poses(hemisphere)
    position = np.where(valid[..., None], position, np.nan)
    quaternion = np.where(valid[..., None], quaternion, np.nan)
    if signal is not None:
        signal = np.where(valid[..., None, None], signal, np.nan)
    return Frames(time, valid, position, quaternion, signal)


def _expected_sensors(step: str, session: Session) -> int | None:
    if step.startswith("cube_"):
        return CUBE_SENSORS
    calibration = session.steps.get("wand_calibration")
    if step != "wand_calibration" and step != "check" and calibration is not None:
        return calibration.n_sensors
    return None


def collect_step(source, step: str, session: Session | None = None, *, rule: StopRule | None = None,
                 frames: int | None = None, duration_s: float | None = None, hemisphere: str | None = None,
                 attrs: dict | None = None, on_status: Callable[[StepStatus], None] | None = None,
                 stop: threading.Event | None = None, read_timeout_s: float = 0.1, status_every_s: float = 0.2,
                 stale_after_s: float = STALE_AFTER_S, idle_limit_s: float | None = None
                 ) -> tuple[Step | None, StepReport]:
    """Record protocol ``step`` from an open live ``source`` until its stop rule is met; the step and a report.

    ``session``: what has been recorded so far (its calibrations gate the wand sweep; its hemisphere and working
    volume are used). ``rule``: the stop rule (default :func:`ivc.collect.rules.default_rule`, or a count of
    ``frames`` / ``duration_s`` seconds of tracker time). ``attrs`` are stored on the step (a cube survey's
    ``declared_position`` and ``declared_quaternion``). ``on_status(StepStatus)`` is called every
    ``status_every_s`` seconds (host clock) and once at the end. ``stop`` ends the step cleanly when set, as
    Ctrl-C does. ``idle_limit_s``: end the step when nothing arrives for this long (host clock; None: wait, or
    :data:`REHEARSAL_IDLE_S` once a rehearsal's labelled frames have come). A source that fails for good (raises an
    ``IvcError``: its retries ran out) ends the step, kept when what was recorded makes a valid step.

    Returns ``(step, report)``; ``step`` is None when ``report.outcome == "dropped"``. Nothing is written here.
    """
    if not is_known_step(step):
        raise InputError(f"unknown step {step!r}; the steps are {', '.join(STEPS)} and extension_sweep_N")
    session = session if session is not None else Session(hemisphere=hemisphere or "+x")
    hemisphere = hemisphere or session.hemisphere
    feed = source if isinstance(source, SourceFeed) else SourceFeed(source)
    rule = rule if rule is not None else default_rule(step, session, frames, duration_s)
    expected = _expected_sensors(step, session)
    recorder: StepRecorder | None = None
    monitor: SensorMonitor | None = None
    following = False  # the source labels its frames and has reached this step's
    restarts = dropped_frames = skipped = 0
    reason: str | None = None
    failure = ""
    stopped = False
    last_status = -np.inf
    last_arrival = _time.monotonic()
    events: list[SourceEvent] = []
    latest = None
    cube = getattr(rule, "cube", None)

    def status(done: bool) -> StepStatus:
        state = rule.state()
        sensors = monitor.states() if monitor else []
        problems = _problem_words(sensors) + state.problems
        problems += [e.message for e in events[-3:] if e.kind not in ("info", "stale", "resumed", "connected")]
        if monitor and monitor.start is not None:
            elapsed = monitor.now - monitor.start
        else:
            elapsed = 0.0
        return StepStatus(step, instruction(step), rule.description, recorder.n_frames if recorder else 0, elapsed,
                          sensors, state.progress, problems, done or state.done, state.thin, state.target,
                          state.points, latest, cube, restarts, state.cells)

    try:
        while reason is None:
            if stop is not None and stop.is_set():
                reason, stopped = "stopped", True
                break
            try:
                items = feed.read(read_timeout_s)
            except IvcError as error:  # the source gave up (its retries ran out): end the step, keep what can be
                reason, failure = "failed", str(error)
                break
            if not items:
                idle = idle_limit_s if idle_limit_s is not None else REHEARSAL_IDLE_S if following else None
                if feed.finished:
                    reason = "ended"
                elif idle is not None and _time.monotonic() - last_arrival > idle:
                    reason, idle_limit_s = "idle", idle
            batch: list[Sample] = []
            for at, item in enumerate(items):
                if isinstance(item, SourceEvent):
                    events.append(item)
                    if recorder is not None:
                        recorder.add(item)
                    continue
                if item.step is not None and item.step != step:
                    if following or step_order(item.step) > step_order(step):
                        feed.push_back(items[at:])  # the rehearsal has moved on: the rest is the next step's
                        reason = "moved on"
                        break
                    skipped += 1  # frames of an earlier step, left over in a rehearsal
                    continue
                following |= item.step == step
                batch.append(item)
            if batch:
                last_arrival = _time.monotonic()
                if recorder is None:
                    n = batch[0].n_sensors
                    if expected is not None and n != expected:
                        raise InputError(f"{step} records {expected} sensors but the source sends {n}: pass "
                                         "sensors= naming them in order, sensor 0 first")
                    names = feed.sensor_names if len(feed.sensor_names) == n else None
                    recorder = StepRecorder(n, names)
                    monitor = SensorMonitor(names or [str(k) for k in range(n)], stale_after_s)
                    for event in events:
                        recorder.add(event)
                restart = rule.update(frames_of(batch, hemisphere))
                if restart is not None:
                    restarts += 1
                    dropped_frames += recorder.n_frames + restart
                    kept_events = recorder.events
                    recorder = StepRecorder(recorder.n_sensors, recorder.sensor_names)
                    recorder.events.extend(kept_events)
                    batch = batch[restart:]
                for sample in batch:
                    recorder.add(sample)
                    for event in monitor.update(sample):
                        events.append(event)
                        recorder.add(event)
                last = batch[-1] if batch else None
                if last is not None and last.position is not None:
                    latest = np.where(np.asarray(last.valid)[:, None], last.position, np.nan)
                if not following and rule.state().done:
                    reason = "done"
            now = _time.monotonic()
            if on_status is not None and now - last_status >= status_every_s:
                last_status = now
                on_status(status(False))
    except KeyboardInterrupt:
        reason, stopped = "stopped", True
    rule.finish()
    final = rule.state()
    usable, why = rule.usable()
    n = recorder.n_frames if recorder else 0
    if reason in ("done", "moved on", "ended", "idle") and following and n:
        outcome, message = "done", f"{step}: recorded the {n:,} frames the source labelled {step}"
        if not final.done:
            message += " (its stop rule was not met: " + "; ".join(
                f"{p.label} {p.value:.4g} of {p.target:.4g} {p.unit}" for p in final.progress if not p.done) + ")"
    elif reason == "done":
        outcome, message = "done", f"{step}: done, the stop rule is met after {n:,} frames"
    else:
        cause = {"stopped": "stopped before its stop rule was met", "ended": "the source ended before the stop rule "
                 "was met", "idle": f"nothing arrived for {idle_limit_s} s", "moved on": "the source moved on to "
                 "the next step before the stop rule was met", "failed": f"the source failed ({failure})"}[reason]
        if usable and n:
            outcome, message = "kept", f"{step}: {cause}; kept as a valid step ({why})"
        else:
            outcome, message = "dropped", f"{step}: {cause}; dropped, nothing kept ({why})"
    if skipped:
        message += f"; skipped {skipped:,} frames labelled with earlier steps"
    if restarts:
        message += f"; restarted {restarts} time{'s' if restarts > 1 else ''} ({dropped_frames:,} frames dropped)"
    if on_status is not None:
        on_status(status(outcome == "done"))
    report = StepReport(step, outcome, message, n, rule.description, final.progress,
                        status(outcome == "done").problems, events, restarts, dropped_frames, stopped)
    if outcome == "dropped" or recorder is None:
        report.outcome = "dropped"
        return None, report
    step_attrs = dict(attrs or {})
    step_attrs.update(guided_rule=rule.description, guided_outcome=outcome, guided_restarts=restarts)
    recorded = recorder.to_step(step, feed.sample_rate_hz, describe_step(step), step_attrs)
    return recorded, report


def collect_protocol(source, steps: Sequence[str] = STEPS, session: Session | None = None, *,
                     output: str | Path | None = None, force: bool = False, hemisphere: str | None = None,
                     declared_position=None, declared_quaternion=None,
                     rules: dict[str, StopRule] | None = None, counts: dict[str, dict] | None = None,
                     on_step_start: Callable[[str, str], None] | None = None,
                     on_status: Callable[[StepStatus], None] | None = None,
                     on_step: Callable[[Step | None, StepReport], None] | None = None,
                     stop: threading.Event | None = None, **options) -> tuple[Session, list[StepReport]]:
    """Walk ``steps`` in protocol order with :func:`collect_step`, each step's kept recording added to the session
    (and, with ``output``, written to that file by :func:`ivc.session.add_step`, atomically, as soon as it is kept).

    ``session``: steps recorded before (default: a new session in ``hemisphere``); ``declared_position`` (3,) m and
    ``declared_quaternion`` (4,) ``[w, x, y, z]``: the cube's declared pose, stored on cube_survey (required when
    it is among ``steps``). ``rules``: a stop rule per step; ``counts``: ``{step: {"frames": N}}`` or
    ``{"duration_s": S}``. ``on_step_start(step, instruction)`` before each step, ``on_step(step, report)`` after.
    The walk ends early when a step is dropped or stopped. Returns the session and every step's report."""
    session = session if session is not None else Session(hemisphere=hemisphere or "+x")
    if hemisphere is not None:
        session.hemisphere = hemisphere
    order = sorted(steps, key=step_order)
    survey_attrs = None
    if "cube_survey" in order:
        if declared_position is None or declared_quaternion is None:
            raise InputError("the cube survey needs the cube's declared pose: pass declared_position (x, y, z m) and "
                             "declared_quaternion (w, x, y, z) of the cube fixture frame in the source frame")
        q = np.asarray(declared_quaternion, float)
        if q.shape != (4,) or abs(np.linalg.norm(q) - 1) > 1e-6:
            raise InputError("declared_quaternion must be a unit quaternion w, x, y, z")
        survey_attrs = {"declared_position": np.asarray(declared_position, float),
                        "declared_quaternion": rotations.canonical(q)}
    output = Path(output) if output is not None else None
    if output is not None and output.exists() and not force:
        existing = [s for s in order if s in _steps_in(output)]
        if existing:
            raise FileExistsError(f"{output}: step(s) {', '.join(existing)} already recorded; pass force=True "
                                  "to replace them")
    feed = source if isinstance(source, SourceFeed) else SourceFeed(source)
    reports = []
    for name in order:
        if on_step_start is not None:
            on_step_start(name, instruction(name))
        rule = (rules or {}).get(name)
        count = (counts or {}).get(name, {})
        step, report = collect_step(feed, name, session, rule=rule, frames=count.get("frames"),
                                    duration_s=count.get("duration_s"), hemisphere=session.hemisphere,
                                    attrs=survey_attrs if name == "cube_survey" else None, on_status=on_status,
                                    stop=stop, **options)
        reports.append(report)
        if step is not None:
            session.steps[name] = step
            if output is not None:
                save_step(output, name, step, session, force)
        if on_step is not None:
            on_step(step, report)
        if step is None or report.stopped:
            break
    return session, reports


def save_step(output: str | Path, name: str, step: Step, session: Session, force: bool = False) -> None:
    """Add a kept step to the session file, atomically; a new file also gets the session's attributes (the
    declared working volume). ``force`` replaces a step already in the file."""
    output = Path(output)
    if output.exists():
        add_step(output, name, step, hemisphere=session.hemisphere, force=force)
    else:
        write(Session(session.hemisphere, {name: step}, attrs=dict(session.attrs)), output)


def _steps_in(path: Path) -> set[str]:
    from ivc.session import read

    return set(read(path).steps)
