"""``igtl://HOST:PORT``: a live source that is an OpenIGTLink client of any tracking server (PLUS, 3D Slicer, Anser
EMT, ``ivc serve``), in the shape of :mod:`ivc.collect.stream`.

Poses come as TRANSFORM (one per tool, PLUS's way), POSITION, TDATA or QTDATA messages, signal matrices as
NDARRAY (3, 3) messages (as ``ivc correct --live`` reads them); translations in ``length_unit`` metres per unit
(millimetres, OpenIGTLink's unit, by default). Messages with the same time stamp are one frame; a frame is complete
when every sensor of the step has sent what the stream carries (its pose, its signal, or both), when a message with
another time stamp arrives, or when nothing has arrived for ``frame_timeout_s`` (its absent sensors then invalid).

Metadata (protocol v2/v3) honoured: ``IGTL_DEVICE_NAME`` (a long device name, instead of the header's 20 bytes);
PLUS's per-tool status ``TransformStatus`` (``OK``, ``MISSING``, ``OUT_OF_VIEW``, ``OUT_OF_VOLUME``,
``REQ_TIMEOUT``, ``INVALID``, ``PATH_NOT_FOUND``, ``UNKNOWN``, ``SWITCHn_IS_ON``; a tool is valid when it is ``OK``
or a switch is on) or, without it, ``TransformValid`` (``1``/``true`` valid); ``IvcStep``, the rehearsal's step
label (``ivc serve``). An invalid tool is stored with ``valid = False``, never as a pose.

The sensor order (sensor 0 first): ``sensors`` (device names, or long names) when given; else the names seen in
the first frame, which must be one tool, or names that each hold a number (the last run of digits: ``Sensor3``,
``cube3``, ``Tool03ToTracker``), all different: ordered by it. Otherwise :meth:`IgtlSource.open` refuses, listing
the names it saw. A rehearsal stream (frames labelled with ``IvcStep``) may change its tools with its step: the
order is then taken again, by the same rule, from the new step's first frame.
"""

from __future__ import annotations

import re
import selectors
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ivc import rotations
from ivc.collect.stream import OpenedByWith, Sample, SourceEvent, StaleWatch
from ivc.errors import LiveError
from ivc.igtl import (
    Framer,
    decode_ndarray,
    decode_position,
    decode_qtdata,
    decode_tdata,
    decode_transforms,
    parse_metadata,
    parse_url,
    split_body,
)

#: metadata keys read (PLUS's names; ``IvcStep`` is ivc's own)
DEVICE_NAME_KEY, STATUS_KEY, VALID_KEY, STEP_KEY = "IGTL_DEVICE_NAME", "TransformStatus", "TransformValid", "IvcStep"
#: PLUS tool statuses under which the pose is a measurement (a switch on a tool does not spoil its pose)
VALID_STATUSES = frozenset({"OK", "SWITCH1_IS_ON", "SWITCH2_IS_ON", "SWITCH3_IS_ON"})
_NUMBER = re.compile(r"(\d+)(?!.*\d)")
_TRUE = frozenset({"1", "true", "yes", "\x01"})
#: parsed metadata kept per distinct raw bytes (a tracker repeats the same few)
_META_CACHE_SIZE = 4096


def sensor_order(names: Sequence[str]) -> list[str]:
    """``names`` in sensor order, by the module's rule (one name, or each name's last number, all different);
    raises LiveError listing them otherwise."""
    names = list(dict.fromkeys(names))
    if len(names) <= 1:
        return names
    numbers = [_NUMBER.search(n) for n in names]
    if all(numbers) and len({int(m.group(1)) for m in numbers}) == len(names):
        return [n for _, n in sorted(zip([int(m.group(1)) for m in numbers], names, strict=True))]
    raise LiveError(f"cannot tell the sensor order of the tools {', '.join(map(repr, sorted(names)))}: their names "
                    "do not each end in a different number; give the order with sensors=[...] (device names, "
                    "sensor 0 first)")


@dataclass
class _Meta:
    name: str | None
    valid: bool
    step: str | None


def _meta(raw: bytes) -> _Meta:
    m = parse_metadata(raw)
    status = m.get(STATUS_KEY)
    if status is not None:
        valid = status.strip().upper() in VALID_STATUSES
    elif VALID_KEY in m:
        valid = m[VALID_KEY].strip().lower() in _TRUE
    else:
        valid = True
    return _Meta(m.get(DEVICE_NAME_KEY) or None, valid, m.get(STEP_KEY) or None)


_NO_META = _Meta(None, True, None)


class IgtlSource(OpenedByWith):
    """An OpenIGTLink client as a :class:`~ivc.collect.stream.LiveSource` (see the module docstring).

    ``sensors``: device names in the step's order (sensor 0 first), else the rule of the module docstring.
    ``discover_s``: at most this long (s) :meth:`open` reads to see the first whole frame's names (nothing read is
    lost). ``stale_after_s``: a sensor whose pose repeats exactly or that stops arriving for this long (source
    clock, and host clock when the whole stream stops) is reported ``stale``. A lost connection is retried every
    ``retry_s`` s, at most ``retries`` times in a row (events ``disconnected``, ``reconnected``); then
    :meth:`read` raises LiveError. The frame being assembled when the connection drops is dropped (said in the
    event), never half-recorded.
    """

    sample_rate_hz: float | None = None

    def __init__(self, host: str, port: int, *, sensors: Sequence[str] | None = None, length_unit: float = 1e-3,
                 discover_s: float = 5.0, stale_after_s: float = 0.5, retries: int = 40, retry_s: float = 0.25,
                 frame_timeout_s: float = 0.25, connect_timeout_s: float = 2.0):
        self.host, self.port = host, int(port)
        self.fixed = sensors is not None
        if sensors is not None:
            sensors = [str(s) for s in sensors]
            if len(set(sensors)) != len(sensors) or not sensors:
                raise LiveError(f"sensors must name each sensor once, got {sensors}")
        self.sensor_names: tuple[str, ...] = tuple(sensors or ())
        self.length_unit = float(length_unit)
        self.discover_s, self.stale_after_s = float(discover_s), float(stale_after_s)
        self.retries, self.retry_s = int(retries), float(retry_s)
        self.frame_timeout_s, self.connect_timeout_s = float(frame_timeout_s), float(connect_timeout_s)
        self._sock: socket.socket | None = None
        self._selector: selectors.BaseSelector | None = None
        self._framer = Framer(decode=False)
        self._meta_cache: dict[bytes, _Meta] = {}
        self._records: list[tuple] = []  # (stamp, name, kind, row, meta, host) not yet assembled
        self._pending: dict | None = None  # the frame being assembled: stamp, host, tools {name: [pose, signal]}
        self._index: dict[str, int] = {n: i for i, n in enumerate(self.sensor_names)}
        self._kinds: set[str] = set()  # "pose", "signal": what the stream carries
        self._step: str | None = None
        self._watch: StaleWatch | None = None
        self._last_host: float | None = None  # host time of the last frame
        self._idle: np.ndarray | None = None
        self._told: set = set()
        self._emitted: float | None = None  # the time stamp of the last frame assembled
        self._last_data = 0.0  # host time the last read that received bytes ended
        self._got_data = False  # whether the current read received bytes
        self._lost: str | None = None  # why the connection ended during the current read
        self._events: list[SourceEvent] = []  # said while decoding, returned by the current read
        self._garbage = 0
        self._failures = 0
        self._next_try = 0.0
        self._opened = False
        #: a rehearsal's sensor names per step label (a Sample carries no names, and they change with the step)
        self.names_by_step: dict[str, tuple[str, ...]] = {}
        self.frames = 0  #: samples returned so far
        self.connections = 0  #: successful connections so far

    @classmethod
    def from_spec(cls, argument: str, *, sensors: Sequence[str] | None = None, hemisphere: str = "+x",
                  **options) -> IgtlSource:
        """``HOST:PORT`` (the part after ``igtl://``); ``hemisphere`` is the server's business (poses arrive solved)."""
        host, port = parse_url(argument)
        return cls(host, port, sensors=sensors, **options)

    # ---- connection -----------------------------------------------------------------------------------------
    def _connect(self) -> bool:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except OSError:
            return False
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self._sock = sock
        self._selector = selectors.DefaultSelector()
        self._selector.register(sock, selectors.EVENT_READ)
        self._framer.clear()
        self.connections += 1
        return True

    def _drop(self, reason: str) -> list[SourceEvent]:
        lost = self._pending is not None or bool(self._records)
        self._close_socket()
        self._pending, self._records = None, []
        self._next_try = time.monotonic()
        self._failures = 0
        return [SourceEvent("disconnected", f"OpenIGTLink server {self.host}:{self.port}: {reason}"
                            + ("; the frame being received was dropped" if lost else "")
                            + f"; reconnecting (at most {self.retries} tries, every {self.retry_s:g} s)")]

    def _close_socket(self) -> None:
        if self._selector is not None:
            self._selector.close()
            self._selector = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _reconnect(self, timeout_s: float) -> list[SourceEvent]:
        deadline = time.monotonic() + timeout_s
        while True:
            now = time.monotonic()
            if now >= self._next_try:
                if self._connect():
                    return [SourceEvent("reconnected", f"reconnected to {self.host}:{self.port} "
                                        f"(connection {self.connections})")]
                self._failures += 1
                if self._failures >= self.retries:
                    raise LiveError(f"lost the OpenIGTLink server {self.host}:{self.port}: {self.retries} "
                                    f"reconnection attempts over {self.retries * self.retry_s:g} s failed; what was "
                                    "recorded before is kept")
                self._next_try = now + self.retry_s
            wait = min(self._next_try, deadline) - time.monotonic()
            if time.monotonic() >= deadline:
                return []
            time.sleep(max(wait, 0.0))

    def open(self) -> None:
        """Connect (refusing after ``retries`` failed attempts) and, without ``sensors``, learn the sensor order
        from the first whole frame (at most ``discover_s`` seconds)."""
        deadline = time.monotonic() + max(self.retries * self.retry_s, self.connect_timeout_s)
        while not self._connect():
            if time.monotonic() >= deadline:
                raise LiveError(f"cannot connect to an OpenIGTLink server at {self.host}:{self.port} (is it "
                                "running, and is the port right?)")
            time.sleep(self.retry_s)
        self._opened = True
        if self.fixed:
            self._set_order(list(self.sensor_names))
            return
        deadline = time.monotonic() + self.discover_s
        while not self._first_frame_known():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            self._receive(min(left, 0.05))
        names = self._first_frame_names()
        if not names:
            self.close()
            raise LiveError(f"the OpenIGTLink server {self.host}:{self.port} sent no tracking message (TRANSFORM, "
                            f"POSITION, TDATA, QTDATA or NDARRAY) within {self.discover_s:g} s")
        try:
            self._set_order(sensor_order(names))
        except LiveError:
            self.close()
            raise

    def _first_frame_known(self) -> bool:
        """Whether a whole frame has been seen: a second time stamp arrived after the first one's tools."""
        return any(r[0] != self._records[0][0] for r in self._records) if self._records else False

    def _first_frame_names(self) -> list[str]:
        if not self._records:
            return []
        first = self._records[0][0]
        return [r[1] for r in self._records if r[0] == first]

    def _set_order(self, names: list[str]) -> None:
        self.sensor_names = tuple(names)
        self._index = {n: i for i, n in enumerate(names)}
        n = len(names)
        self._watch = StaleWatch(n, self.stale_after_s, names=names)
        self._last_host = time.monotonic()
        self._idle = np.zeros(n, bool)

    def close(self) -> None:
        self._close_socket()
        self._opened = False

    # ---- reading --------------------------------------------------------------------------------------------
    def _receive(self, timeout_s: float) -> list[SourceEvent]:
        """Read what the socket holds (waiting up to ``timeout_s``) into decoded records."""
        if self._sock is None:
            return []
        if not self._selector.select(timeout_s):
            return []
        chunks = []
        while True:
            try:
                data = self._sock.recv(1 << 20)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as error:
                self._lost = f"connection lost ({error.strerror or error})"
                break
            if not data:
                self._lost = "connection closed by the server"
                break
            chunks.append(data)
            if len(data) < 1 << 20:
                break
        return self._feed(chunks)

    def _feed(self, chunks: list[bytes]) -> list[SourceEvent]:
        events = []
        if chunks:
            self._got_data = True
            self._framer.feed(b"".join(chunks))
        self._decode(self._framer.messages())
        if self._framer.garbage > self._garbage:
            events.append(SourceEvent("garbage", f"skipped {self._framer.garbage - self._garbage} malformed bytes "
                                      "from the OpenIGTLink server (no valid header or CRC); resynchronised on the "
                                      "next valid message"))
            self._garbage = self._framer.garbage
        return events

    def _meta_of(self, raw: bytes) -> _Meta:
        if not raw:
            return _NO_META
        meta = self._meta_cache.get(raw)
        if meta is None:
            if len(self._meta_cache) >= _META_CACHE_SIZE:
                self._meta_cache.clear()
            meta = self._meta_cache[raw] = _meta(raw)
        return meta

    def _decode(self, messages) -> None:
        """Messages → records (stamp, name, pose row or signal, valid, step); TRANSFORMs decoded all at once."""
        if not messages:
            return
        host = time.monotonic()
        transforms, rows = [], []  # TRANSFORM contents, their records' indices
        records = self._records
        positions, quaternions = [], []  # poses of POSITION / TDATA / QTDATA elements (stream unit, [w,x,y,z])
        for m in messages:
            kind = m.message_type
            if kind not in ("TRANSFORM", "POSITION", "TDATA", "QTDATA", "NDARRAY"):
                self._tell(("type", kind), f"ignoring {kind} messages (poses come as TRANSFORM, POSITION, TDATA or "
                           "QTDATA, signal matrices as NDARRAY)")
                continue
            content, raw = split_body(m.version, m.body)
            meta = self._meta_of(raw)
            name = meta.name or m.device_name
            try:
                if kind == "TRANSFORM":
                    if len(content) != 48:
                        raise ValueError
                    rows.append(len(records))
                    transforms.append(content)
                    records.append([m.timestamp, name, "pose", None, meta, host])
                elif kind == "NDARRAY":
                    a = decode_ndarray(content)
                    if a.shape != (3, 3):
                        self._tell(("shape", name), f"tool {name!r}: an NDARRAY of shape {a.shape} is not a 3x3 "
                                   "signal matrix; ignored")
                        continue
                    records.append([m.timestamp, name, "signal", a, meta, host])
                elif kind == "POSITION":
                    p, q = decode_position(content)
                    records.append([m.timestamp, name, "pose", -1 - len(positions), meta, host])
                    positions.append(p)
                    quaternions.append(q)
                else:
                    if kind == "TDATA":
                        names, matrices = decode_tdata(content)
                        p, q = matrices[:, :3, 3], rotations.from_matrix(matrices[:, :3, :3])
                    else:
                        names, p, q = decode_qtdata(content)
                    for k, tool in enumerate(names):
                        records.append([m.timestamp, tool, "pose", -1 - len(positions), meta, host])
                        positions.append(p[k])
                        quaternions.append(q[k])
            except (ValueError, IndexError):
                self._framer.bad += 1
                self._tell(("bad", kind), f"dropped a {kind} message whose content could not be decoded")
        if transforms:
            m = decode_transforms(b"".join(transforms))
            p, q = self._poses(m[:, :3, 3], rotations.from_matrix(m[:, :3, :3]))
            for k, r in enumerate(rows):
                records[r][3] = (p[k], q[k]) if p[k] is not None else None
        if positions:
            p, q = self._poses(np.asarray(positions), np.asarray(quaternions))
            for r in records:
                if isinstance(r[3], int):
                    k = -1 - r[3]
                    r[3] = (p[k], q[k]) if p[k] is not None else None

    def _poses(self, position: np.ndarray, quaternion: np.ndarray) -> tuple[list, list]:
        """Decoded poses (stream unit, quaternions) → rows in metres and unit quaternions, None where not finite."""
        position = position * self.length_unit
        with np.errstate(all="ignore"):
            quaternion = quaternion / np.linalg.norm(quaternion, axis=1, keepdims=True)
        finite = np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(quaternion), axis=1)
        rows_p, rows_q = list(position), list(quaternion)
        for k in np.flatnonzero(~finite):
            rows_p[k] = rows_q[k] = None
        return rows_p, rows_q

    def _tell(self, key, message: str) -> None:
        if key not in self._told:
            self._told.add(key)
            self._events.append(SourceEvent("info", message))

    def _gather(self) -> list[Sample]:
        """Assemble records into frames by time stamp; the samples of the frames completed."""
        out = []
        for stamp, name, kind, value, meta, host in self._records:
            if stamp == self._emitted and self._pending is None:  # a late part of a frame already complete
                if name in self._index:
                    self._tell(("late", name), f"tool {name!r}: a message arrived after its frame was complete "
                               "(a repeated time stamp); ignored")
                continue
            p = self._pending
            if p is not None and p["stamp"] != stamp:
                out += self._emit()
                p = None
            if p is None:
                p = self._pending = {"stamp": stamp, "host": host, "tools": {}, "step": None, "whole": 0}
            tool = p["tools"].get(name)
            if tool is None:
                tool = p["tools"][name] = {}
            tool[kind] = (value, meta.valid)
            if kind not in self._kinds:
                self._kinds.add(kind)
            if meta.step is not None:
                p["step"] = meta.step
            if len(tool) == len(self._kinds) and name in self._index:  # this tool is whole
                p["whole"] += 1
                if p["whole"] >= len(self._index) and self._opened and self._complete(p):
                    out += self._emit()
        self._records = []
        return out

    def _quiet(self) -> list[Sample]:
        """The frame being assembled, if the stream has been quiet for ``frame_timeout_s`` (waited for, not spent
        decoding a backlog): its absent sensors are invalid."""
        out = []
        if self._pending is not None and self._index and time.monotonic() - self._last_data > self.frame_timeout_s:
            out += self._emit()
        return out

    def _complete(self, p) -> bool:
        tools = p["tools"]
        if len(tools) < len(self._index):
            return False
        return all(n in tools and all(k in tools[n] for k in self._kinds) for n in self._index)

    def _emit(self) -> list[Sample]:
        p, self._pending = self._pending, None
        if self._emitted is not None and p["stamp"] < self._emitted:
            self._events.append(SourceEvent("reset", f"the stream's time went back {self._emitted - p['stamp']:.3f} s "
                                            "(the server restarted, or its clock was reset)", time=p["stamp"]))
        self._emitted = p["stamp"]
        if not self._index and not self._opened:
            return []
        step = p["step"]
        if step is not None and step != self._step and not self.fixed and self._step is not None:
            names = list(p["tools"])
            if set(names) != set(self._index):
                try:
                    self._set_order(sensor_order(names))
                    self._events.append(SourceEvent("info", f"step {step!r}: sensor order "
                                                    f"{', '.join(self.sensor_names)}"))
                except LiveError as error:
                    self._events.append(SourceEvent("info", f"step {step!r}: {error}"))
        self._step = step if step is not None else self._step
        if step is not None:
            self.names_by_step.setdefault(step, self.sensor_names)
        n = len(self._index)
        has_pose, has_signal = "pose" in self._kinds, "signal" in self._kinds
        index, rows, positions, quaternions, signals = self._index, [], [], [], []
        for name, tool in p["tools"].items():
            i = index.get(name)
            if i is None:
                self._tell(("unknown", name), f"ignoring tool {name!r}: not one of the sensors "
                           f"{', '.join(self.sensor_names)}")
                continue
            if has_pose:
                pose = tool.get("pose")
                if pose is None or not pose[1] or pose[0] is None:  # absent, a PLUS status, or not finite
                    continue
            if has_signal:
                sig = tool.get("signal")
                if sig is None or not sig[1] or not np.all(np.isfinite(sig[0])):
                    continue
                signals.append(sig[0])
            if has_pose:
                positions.append(pose[0][0])
                quaternions.append(pose[0][1])
            rows.append(i)
        valid = np.zeros(n, bool)
        valid[rows] = True
        position = quaternion = signal = None
        if has_pose:
            position, quaternion = np.full((n, 3), np.nan), np.full((n, 4), np.nan)
            if rows:
                position[rows], quaternion[rows] = positions, quaternions
        if has_signal:
            signal = np.full((n, 3, 3), np.nan)
            if rows:
                signal[rows] = signals
        sample = Sample(time=float(p["stamp"]), valid=valid, position=position, quaternion=quaternion, signal=signal,
                        host_time=p["host"], step=step)
        self._last_host = p["host"]
        self.frames += 1
        return [sample]

    def read(self, timeout_s: float) -> list[Sample | SourceEvent]:
        """What arrived within ``timeout_s`` s: samples in order, with events (drops, garbage, stale sensors)."""
        if not self._opened:
            raise LiveError("open the igtl:// source before reading it (use it in a with statement)")
        events: list[SourceEvent] = []
        if self._sock is None:
            events += self._reconnect(timeout_s)
            if self._sock is None:
                told, self._events = self._events, []
                return told + events + self._idle_events()
        self._got_data = False
        events += self._receive(timeout_s)
        samples = self._gather()
        if self._got_data:
            self._last_data = time.monotonic()  # after the decoding: its time is not the stream's silence
        else:
            samples += self._quiet()
        if self._lost is not None:  # what arrived whole before the drop is kept; the frame it cut is not
            events += self._drop(self._lost)
            self._lost = None
        out: list[Sample | SourceEvent] = []
        out += events
        for sample in samples:
            if self._watch.n_sensors != sample.n_sensors:
                self._watch = StaleWatch(sample.n_sensors, self.stale_after_s, names=self.sensor_names)
            out += self._watch.update(sample)
            out.append(sample)
            for i in np.flatnonzero(self._idle[:sample.n_sensors]):
                self._idle[i] = False
                out.append(SourceEvent("resumed", f"sensor {i} ({self.sensor_names[i]}) is arriving again",
                                       sensor=int(i), time=sample.time))
        told, self._events = self._events, []  # said while decoding (here or while opening)
        return told + out + self._idle_events()

    def _idle_events(self) -> list[SourceEvent]:
        """When the whole stream stops (by the host clock), each sensor not already stale: one that stops
        while the others stream is :class:`StaleWatch`'s (its samples then arrive invalid)."""
        if self._last_host is None:
            return []
        now = time.monotonic()
        if now - self._last_host < self.stale_after_s:
            return []
        silent = ~self._idle
        if self._watch is not None and self._watch.n_sensors == len(silent):
            silent &= ~self._watch.stale
        out = []
        for i in np.flatnonzero(silent):
            self._idle[i] = True
            out.append(SourceEvent("stale", f"sensor {i} ({self.sensor_names[i]}) stale: nothing received for "
                                   f"{now - self._last_host:.1f} s", sensor=int(i)))
        return out
