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

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from ivc.errors import SessionError
from ivc.session import Step, describe_step

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
