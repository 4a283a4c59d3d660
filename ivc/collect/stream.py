"""Live sources: the one shape every streaming source yields, and the recorder that turns it into a step.

A live source (an OpenIGTLink client, a Polhemus serial port, the simulator run in real time, a replayed file)
is opened, read in short calls, and closed. Each :meth:`LiveSource.read` returns what arrived since the last
call: :class:`Sample` objects (one tracker frame of all sensors) and :class:`SourceEvent` objects (the source
connected, dropped, was reset, sent garbage, ...). Nothing in a source decides whether a step is good: it
reports what the device said, and :class:`StepRecorder` keeps every frame as it was recorded.

Units and frames: positions in metres and quaternions ``[w, x, y, z]`` (Hamilton, sensor to source) in the
source frame, as in the session file (docs/conventions.md); signal matrices (3, 3) in the ideal dipole units of
docs/conventions.md. Times in seconds on the *source's* clock (a device's frame count over its rate, or the
message time stamps), never the host's receive time, which only :attr:`Sample.host_time` carries.
"""

from __future__ import annotations

import time as _time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol, Self, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from ivc.errors import SessionError
from ivc.session import Step, describe_step, step_order

#: what a :class:`SourceEvent` can report
EventKind = Literal["connected", "disconnected", "reconnected", "reset", "stale", "resumed", "garbage", "info"]


@dataclass(frozen=True)
class Sample:
    """One tracker frame of all N sensors, in the step's sensor order (sensor 0 first).

    ``position`` (N, 3) m and ``quaternion`` (N, 4) in the source frame, or ``signal`` (N, 3, 3), or both;
    ``valid`` (N,) is False for a sensor the device reported missing, out of range or in error (its pose is
    then NaN, never a made-up value). ``time`` is seconds on the source's clock; ``frame`` the device's own
    frame counter where it has one; ``host_time`` the host's ``time.monotonic()`` at receipt (for rate and
    latency checks only)."""

    time: float
    valid: NDArray[np.bool_]
    position: NDArray[np.float64] | None = None
    quaternion: NDArray[np.float64] | None = None
    signal: NDArray[np.float64] | None = None
    frame: int | None = None
    host_time: float | None = None
    #: the protocol step this frame belongs to, where the source knows it: only rehearsal sources (a replayed
    #: session, ``ivc serve sim``) label their frames; a real tracker never does
    step: str | None = None

    def __post_init__(self) -> None:
        n = np.shape(self.valid)[0] if np.ndim(self.valid) == 1 else -1
        if n < 0:
            raise SessionError(f"a live sample's valid must be one flag per sensor, got shape {np.shape(self.valid)}")
        if self.position is None and self.signal is None:
            raise SessionError("a live sample carries a pose (position and quaternion) or a signal matrix, or both")
        if (self.position is None) != (self.quaternion is None):
            raise SessionError("a live sample's position and quaternion come together")
        for name, shape in (("position", (n, 3)), ("quaternion", (n, 4)), ("signal", (n, 3, 3))):
            value = getattr(self, name)
            if value is not None and np.shape(value) != shape:
                raise SessionError(f"a live sample's {name} must have shape {shape} for {n} sensors, "
                                   f"got {np.shape(value)}")

    @property
    def n_sensors(self) -> int:
        return int(np.shape(self.valid)[0])


@dataclass(frozen=True)
class SourceEvent:
    """Something the source noticed besides a frame, in words a person can act on.

    ``sensor`` is the sensor's index in the step's order when the event concerns one sensor (``stale``,
    ``resumed``), else None; ``time`` is on the source's clock where known."""

    kind: EventKind
    message: str
    sensor: int | None = None
    time: float | None = None


@runtime_checkable
class LiveSource(Protocol):
    """What every live source offers. Use it as a context manager (``with source: ...``), which opens and
    closes it.

    ``sensor_names`` are known after :meth:`open` (device names, station numbers as strings, ...), in the step's
    order; ``sample_rate_hz`` is the device's nominal rate where it states one, else None. :meth:`read` waits at
    most ``timeout_s`` seconds for something to arrive and returns all that did (an empty list when nothing did);
    it survives garbage and drops (reporting them as events) and raises an ``IvcError`` only when the source
    cannot go on (for example its retries ran out)."""

    sensor_names: tuple[str, ...]
    sample_rate_hz: float | None

    def open(self) -> None: ...

    def read(self, timeout_s: float) -> list[Sample | SourceEvent]: ...

    def close(self) -> None: ...

    def __enter__(self) -> LiveSource: ...

    def __exit__(self, *exc) -> None: ...


class OpenedByWith:
    """A source's ``with`` form: :meth:`open` on entering, :meth:`close` on leaving (what :class:`LiveSource`
    asks); the live sources inherit it."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class StepRecorder:
    """Keeps every frame of a live step as recorded, and makes the session step from them.

    The gates of guided collection decide nothing here: invalid samples are stored with ``valid = False``
    (their poses NaN), so that ``ivc fixtures`` can redo any decision."""

    n_sensors: int
    sensor_names: Sequence[str] | None = None
    times: list[float] = field(default_factory=list)
    valids: list[NDArray[np.bool_]] = field(default_factory=list)
    positions: list[NDArray[np.float64]] = field(default_factory=list)
    quaternions: list[NDArray[np.float64]] = field(default_factory=list)
    signals: list[NDArray[np.float64]] = field(default_factory=list)
    events: list[SourceEvent] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.times)

    def add(self, item: Sample | SourceEvent) -> None:
        """Record one sample (or keep one event for the step's log)."""
        if isinstance(item, SourceEvent):
            self.events.append(item)
            return
        if item.n_sensors != self.n_sensors:
            raise SessionError(f"a live sample has {item.n_sensors} sensors, the step records {self.n_sensors}")
        if self.times and (item.position is None) != (not self.positions):
            raise SessionError("a live source switched between poses and signals mid-step")
        if self.times and (item.signal is None) != (not self.signals):
            raise SessionError("a live source switched between poses and signals mid-step")
        valid = np.asarray(item.valid, dtype=bool).copy()
        self.times.append(float(item.time))
        self.valids.append(valid)
        if item.position is not None:
            position = np.array(item.position, dtype=float)
            quaternion = np.array(item.quaternion, dtype=float)
            position[~valid] = np.nan
            quaternion[~valid] = np.nan
            self.positions.append(position)
            self.quaternions.append(quaternion)
        if item.signal is not None:
            signal = np.array(item.signal, dtype=float)
            signal[~valid] = np.nan
            self.signals.append(signal)

    def to_step(self, name: str, sample_rate_hz: float | None = None, description: str = "",
                attrs: dict | None = None) -> Step:
        """The recorded frames as a session :class:`~ivc.session.Step` (times made relative to the first
        frame's). ``sample_rate_hz`` defaults to the median frame interval's rate."""
        if not self.times:
            raise SessionError(f"step {name!r} recorded no frame: nothing to keep")
        time = np.asarray(self.times, dtype=float)
        time = time - time[0]
        if sample_rate_hz is None:
            steps = np.diff(time)
            steps = steps[steps > 0]
            sample_rate_hz = float(1.0 / np.median(steps)) if steps.size else 240.0
        return Step(
            time=time,
            signal=np.stack(self.signals) if self.signals else None,
            position=np.stack(self.positions) if self.positions else None,
            quaternion=np.stack(self.quaternions) if self.quaternions else None,
            valid=np.stack(self.valids),
            sample_rate_hz=float(sample_rate_hz),
            sensor_ids=list(self.sensor_names) if self.sensor_names is not None else None,
            description=description or describe_step(name),
            attrs=dict(attrs or {}),
        )


@dataclass
class StaleWatch:
    """Tells when a sensor goes stale (its pose repeats exactly, or it stops arriving valid) and when it resumes.

    Feed it every sample with :meth:`update`; it returns the events for that sample. A sensor is stale once its
    last change (or its last valid sample) is at least ``after_s`` seconds old on the source's clock. Exact
    repeats are a tracker's sign that it re-sent an old frame (a real sensor's pose always carries noise);
    :meth:`idle` reports sensors whose samples stopped arriving altogether, by the host clock."""

    n_sensors: int
    after_s: float = 0.5
    names: Sequence[str] | None = None
    _changed: NDArray[np.float64] | None = None
    _last: NDArray[np.float64] | None = None
    _stale: NDArray[np.bool_] | None = None

    def _name(self, sensor: int) -> str:
        return f"sensor {sensor}" + (f" ({self.names[sensor]})" if self.names is not None else "")

    def update(self, sample: Sample) -> list[SourceEvent]:
        """The stale / resumed events this sample causes (source clock)."""
        values = sample.position if sample.position is not None else sample.signal
        flat = np.asarray(values, dtype=float).reshape(self.n_sensors, -1)
        if sample.quaternion is not None:
            flat = np.concatenate([flat, np.asarray(sample.quaternion, dtype=float)], axis=1)
        if self._changed is None:
            self._changed = np.full(self.n_sensors, float(sample.time))
            self._last = flat.copy()
            self._stale = np.zeros(self.n_sensors, dtype=bool)
        moved = np.asarray(sample.valid, dtype=bool) & np.any(flat != self._last, axis=1)
        self._changed[moved] = sample.time
        self._last = flat.copy()
        age = float(sample.time) - self._changed
        stale = age >= self.after_s
        events = []
        for sensor in np.flatnonzero(stale & ~self._stale):
            events.append(SourceEvent("stale", f"{self._name(sensor)} stale: no new valid pose for "
                                      f"{age[sensor]:.1f} s", sensor=int(sensor), time=float(sample.time)))
        for sensor in np.flatnonzero(~stale & self._stale):
            events.append(SourceEvent("resumed", f"{self._name(sensor)} is reporting again", sensor=int(sensor),
                                      time=float(sample.time)))
        self._stale = stale
        return events

    @property
    def stale(self) -> NDArray[np.bool_]:
        """(N,) True for the sensors stale as of the last sample."""
        return np.zeros(self.n_sensors, dtype=bool) if self._stale is None else self._stale.copy()


class SessionSource(OpenedByWith):
    """A live source that streams a session's steps as a tracker would: the rehearsal and test source.

    Streams ``steps`` (default: all of the session's steps in recording order) frame by frame, each
    :class:`Sample` labelled with its step (``Sample.step``) and timed on one continuous clock: each step's
    frames keep their spacing, and ``pause_s`` seconds of tracker time separate two steps (the person moving
    the fixtures; nothing is streamed then). ``realtime`` paces :meth:`read` by the host clock at ``speed``
    times the tracker's rate (``speed = inf`` streams as fast as it is read); without it every read returns
    ``chunk`` frames at once. Signals and/or poses are streamed as the session holds them; ``poses_only``
    drops the signals (what a PLUS user receives)."""

    def __init__(self, session, steps: Sequence[str] | None = None, *, pause_s: float = 0.0,
                 realtime: bool = False, speed: float = 1.0, chunk: int = 256, poses_only: bool = False,
                 clock=None):
        names = list(steps) if steps is not None else sorted(session.steps, key=step_order)
        missing = [n for n in names if n not in session.steps]
        if missing:
            raise SessionError(f"the session has no step {missing[0]!r}; it holds {sorted(session.steps)}")
        if not names:
            raise SessionError("nothing to stream: the session holds no step")
        counts = {session.steps[n].n_sensors for n in names}
        self.session = session
        self.steps = names
        self.hemisphere = session.hemisphere
        self.poses_only = poses_only
        self.pause_s = float(pause_s)
        self.realtime = realtime
        self.speed = float(speed)
        self.chunk = int(chunk)
        self._clock = clock or _time.monotonic
        self.n_sensors_by_step = {n: session.steps[n].n_sensors for n in names}
        first = session.steps[names[0]]
        self.sensor_names = tuple(first.names) if len(counts) == 1 else tuple(str(i) for i in range(max(counts)))
        self.sample_rate_hz = float(first.sample_rate_hz)
        self._items: list[tuple[str, int, float]] | None = None
        self._arrays: dict[str, tuple] = {}
        self._at = 0
        self._start: float | None = None

    def _streamed(self, step: Step) -> tuple:
        """What each frame of ``step`` streams: ``(valid, position, quaternion, signal)`` arrays (or None), made
        once per step (the closed-form poses of a signal-only step, for ``poses_only``, included)."""
        signal = None if self.poses_only or step.signal is None else step.signal
        position = quaternion = None
        if step.position is not None:
            position, quaternion = step.position, step.quaternion
        elif self.poses_only:
            position, quaternion = step.poses(self.hemisphere)
        return step.valid_mask, position, quaternion, signal

    def open(self) -> None:
        items = []
        offset = 0.0
        self._arrays = {name: self._streamed(self.session.steps[name]) for name in self.steps}
        for number, name in enumerate(self.steps):
            step = self.session.steps[name]
            time = np.asarray(step.time, dtype=float)
            if number:
                offset += self.pause_s - float(time[0])
            items.extend((name, f, offset + float(time[f])) for f in range(step.n_frames))
            offset = items[-1][2] + 1.0 / float(step.sample_rate_hz)
        self._items = items
        self._at = 0
        self._start = None

    def __len__(self) -> int:
        return sum(self.session.steps[n].n_frames for n in self.steps)

    def _sample(self, name: str, f: int, t: float) -> Sample:
        valid, position, quaternion, signal = self._arrays[name]
        return Sample(time=t, valid=valid[f], position=None if position is None else position[f],
                      quaternion=None if quaternion is None else quaternion[f],
                      signal=None if signal is None else signal[f], frame=None, host_time=self._clock(), step=name)

    def read(self, timeout_s: float) -> list[Sample | SourceEvent]:
        """The next frames: ``chunk`` of them, or in real time those due by now (waiting up to ``timeout_s``
        for the next one)."""
        if self._items is None:
            raise SessionError("open the source before reading it (use it in a with statement)")
        if self._at >= len(self._items):
            return []
        if not self.realtime or not np.isfinite(self.speed):
            stop = min(self._at + self.chunk, len(self._items))
        else:
            if self._start is None:
                self._start = self._clock() - self._items[self._at][2] / self.speed
            due = (self._clock() - self._start) * self.speed
            wait = self._items[self._at][2] - due
            if wait > 0:
                _time.sleep(min(wait / self.speed, timeout_s))
                due = (self._clock() - self._start) * self.speed
            stop = self._at
            while stop < len(self._items) and self._items[stop][2] <= due and stop - self._at < 100_000:
                stop += 1
        out = [self._sample(*self._items[i]) for i in range(self._at, stop)]
        self._at = stop
        return out

    @property
    def finished(self) -> bool:
        return self._items is not None and self._at >= len(self._items)

    def close(self) -> None:
        self._items = None
        self._arrays = {}

    @classmethod
    def from_spec(cls, argument: str, *, sensors: Sequence[str] | None = None, hemisphere: str = "+x",
                  **options) -> SessionSource:
        """``replay:FILE``: a session file streamed as fast as it is read (``sensors`` and ``hemisphere`` are the
        file's own)."""
        from ivc.session import read

        return cls(read(argument), **options)

