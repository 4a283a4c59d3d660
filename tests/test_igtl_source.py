"""The igtl:// live source against an emulated OpenIGTLink server (messages written from the protocol description,
PLUS's status metadata): message types, statuses, names, sensor order, garbage, drops, restarts and stale tools."""

import socket
import threading
import time

import numpy as np
import pytest

from ivc import rotations
from ivc.collect.igtl import IgtlSource, sensor_order
from ivc.collect.sources import open_live_source
from ivc.collect.stream import Sample, SourceEvent, StepRecorder
from ivc.errors import LiveError
from ivc.igtl import TDATA_ELEMENT, encode_position, encode_qtdata, ndarray_content, pack_message, transform_contents

BASE = 1_700_000_000.0
DEADLINE_S = 30.0


class Emulator:
    """A one-client-at-a-time OpenIGTLink server on 127.0.0.1 that sends what the test gives it (what is given
    before a client connects waits for it)."""

    def __init__(self, port: int = 0):
        self.listener = socket.create_server(("127.0.0.1", port))
        self.port = self.listener.getsockname()[1]
        self.conn: socket.socket | None = None
        self.lock = threading.Lock()
        self.waiting = b""
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        try:
            conn, _ = self.listener.accept()
        except OSError:
            return
        with self.lock:
            self.conn = conn
            conn.sendall(self.waiting)
            self.waiting = b""

    def send(self, data: bytes) -> None:
        with self.lock:
            if self.conn is None:
                self.waiting += data
            else:
                self.conn.sendall(data)

    def drop(self) -> None:
        """Close the client's connection and accept the next one."""
        with self.lock:
            self.conn.close()
            self.conn = None
        threading.Thread(target=self._accept, daemon=True).start()

    def stop(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.listener.close()


def transform(name, stamp, position_mm, quaternion, metadata=None):
    m = np.eye(4)
    m[:3, :3] = rotations.to_matrix(quaternion)
    m[:3, 3] = position_mm
    return pack_message("TRANSFORM", name, stamp, transform_contents(m[None])[0].tobytes(), metadata)


def poses(rng, frames, sensors):
    return rng.uniform(-300, 300, (frames, sensors, 3)), rotations.random((frames, sensors), rng)


def read_until(source, count, events=None, out=None):
    """Samples from ``source`` until ``count`` have arrived (or, with ``out``, until ``out`` holds ``count``; events
    kept in ``events``), within DEADLINE_S."""
    out = [] if out is None else out
    deadline = time.monotonic() + DEADLINE_S
    while len(out) < count:
        assert time.monotonic() < deadline, f"only {len(out)} of {count} frames arrived"
        for item in source.read(0.2):
            (out if isinstance(item, Sample) else events if events is not None else []).append(item)
    return out


def wait_for_event(source, kind, events):
    deadline = time.monotonic() + DEADLINE_S
    while not any(e.kind == kind for e in events):
        assert time.monotonic() < deadline, f"no {kind} event; had {[e.message for e in events]}"
        events += [i for i in source.read(0.1) if isinstance(i, SourceEvent)]
    return [e for e in events if e.kind == kind]


def same_rotation(a, b, atol=2e-6):
    return np.allclose(np.abs(np.sum(a * b, axis=-1)), 1.0, atol=atol)


@pytest.fixture
def server():
    emulator = Emulator()
    yield emulator
    emulator.stop()


@pytest.mark.parametrize("kind", ["TRANSFORM", "TRANSFORM_v2", "POSITION", "TDATA", "QTDATA", "NDARRAY"])
def test_each_message_type_round_trips(server, rng, kind):
    frames, names = 6, ["Tool0", "Tool1", "Tool2"]
    p, q = poses(rng, frames, 3)
    signals = rng.normal(size=(frames, 3, 3, 3))
    data = b""
    for f in range(frames):
        stamp = BASE + f / 240.0
        if kind == "TDATA":
            m = np.zeros((3, 4, 4))
            m[:, :3, :3], m[:, :3, 3] = rotations.to_matrix(q[f]), p[f]
            elements = np.zeros(3, TDATA_ELEMENT)
            elements["name"] = [n.encode() for n in names]
            elements["matrix"] = transform_contents(m)
            data += pack_message("TDATA", "Tracker", stamp, elements.tobytes())
        elif kind == "QTDATA":
            data += pack_message("QTDATA", "Tracker", stamp, encode_qtdata(names, p[f], q[f]))
        for s, name in enumerate(names):
            if kind.startswith("TRANSFORM"):
                data += transform(name, stamp, p[f, s], q[f, s], {} if kind.endswith("v2") else None)
            elif kind == "POSITION":
                data += pack_message("POSITION", name, stamp, encode_position(p[f, s], q[f, s]))
            elif kind == "NDARRAY":
                data += pack_message("NDARRAY", name, stamp, ndarray_content(signals[f, s]))
    server.send(data)
    with IgtlSource("127.0.0.1", server.port) as source:
        assert source.sensor_names == tuple(names)
        got = read_until(source, frames)
    assert [s.time for s in got] == pytest.approx(BASE + np.arange(frames) / 240.0, abs=1e-6)
    assert all(s.valid.all() for s in got)
    if kind == "NDARRAY":
        assert np.array_equal(np.array([s.signal for s in got]), signals)  # float64 matrices, exactly
    else:
        position = np.array([s.position for s in got])
        assert np.allclose(position, p / 1000.0, atol=1e-7)  # mm (float32) to m
        assert same_rotation(np.array([s.quaternion for s in got]), q)


STATUSES = {"OK": True, "MISSING": False, "OUT_OF_VIEW": False, "OUT_OF_VOLUME": False, "REQ_TIMEOUT": False,
            "INVALID": False, "PATH_NOT_FOUND": False, "UNKNOWN": False, "SWITCH1_IS_ON": True}


def test_each_plus_status_and_long_names(server, rng):
    """TransformStatus (all of PLUS's values), TransformValid without a status, and IGTL_DEVICE_NAME long names: an
    invalid tool is stored invalid with a NaN pose, never as a pose."""
    long_names = ["LibertyStation00ToTrackerReference", "LibertyStation01ToTrackerReference"]
    cases = [{"TransformStatus": s, "TransformValid": "1" if v else "0"} for s, v in STATUSES.items()]
    cases += [{"TransformValid": "0"}, {"TransformValid": "1"}, {"TransformValid": "false"}, {}]
    expected = [*STATUSES.values(), False, True, False, True]
    p, q = poses(rng, len(cases), 2)
    data = b""
    for f, meta in enumerate(cases):
        for s, name in enumerate(long_names):
            status = meta if s == 1 else {"TransformStatus": "OK"}
            data += transform(name[:20], BASE + f / 240, p[f, s], q[f, s], {"IGTL_DEVICE_NAME": name, **status})
    server.send(data)
    with IgtlSource("127.0.0.1", server.port, sensors=long_names[::-1]) as source:
        got = read_until(source, len(cases))
        assert source.sensor_names == tuple(long_names[::-1])
    valid = np.array([s.valid for s in got])
    assert valid[:, 1].all() and list(valid[:, 0]) == expected  # sensors=... put station 01 first
    position = np.array([s.position for s in got])
    assert np.isnan(position[~valid[:, 0], 0]).all()
    assert np.allclose(position[valid[:, 0], 0], p[valid[:, 0], 1] / 1000.0, atol=1e-7)
    recorder = StepRecorder(2, long_names[::-1])
    for s in got:
        recorder.add(s)
    step = recorder.to_step("cube_survey")
    assert np.array_equal(step.valid_mask[:, 0], expected) and np.isnan(step.quaternion[~valid[:, 0], 0]).all()


def test_sensor_order_rule_and_refusal(server, rng):
    assert sensor_order(["Sensor10ToTracker", "Sensor2ToTracker", "Sensor0ToTracker"]) == [
        "Sensor0ToTracker", "Sensor2ToTracker", "Sensor10ToTracker"]
    assert sensor_order(["Stylus"]) == ["Stylus"]
    with pytest.raises(LiveError, match="'Probe', 'Stylus'"):
        sensor_order(["Stylus", "Probe"])
    with pytest.raises(LiveError, match="'Tool1', 'Wand1'"):
        sensor_order(["Tool1", "Wand1"])
    p, q = poses(rng, 3, 2)
    server.send(b"".join(transform(n, BASE + f, p[f, s], q[f, s]) for f in range(3)
                         for s, n in enumerate(["Stylus", "Probe"])))
    with pytest.raises(LiveError, match="'Probe', 'Stylus'.*sensors="):
        IgtlSource("127.0.0.1", server.port).open()


def test_sensors_mapping_ignores_other_tools_and_marks_absent_ones(server, rng):
    p, q = poses(rng, 4, 3)
    server.send(b"".join(transform(n, BASE + f, p[f, s], q[f, s]) for f in range(4)
                         for s, n in enumerate(["A", "B", "Extra"])))
    with IgtlSource("127.0.0.1", server.port, sensors=["B", "A", "Never"], frame_timeout_s=0.05) as source:
        events = []
        got = read_until(source, 4, events)
    assert all(list(s.valid) == [True, True, False] for s in got)
    assert np.allclose([s.position[0] for s in got], p[:, 1] / 1000.0, atol=1e-7)
    assert any("'Extra'" in e.message for e in events)


def test_garbage_a_dropped_connection_and_a_server_restart_are_survived(rng):
    """Frames on both sides of garbage, a dropped connection (cutting a frame) and a server restart on the same
    port arrive whole; the cut frame is dropped, never recorded half."""
    names = ["S0", "S1", "S2"]
    p, q = poses(rng, 40, 3)

    def frame(f, sensors=names):
        return b"".join(transform(n, BASE + f / 240, p[f, s], q[f, s]) for s, n in enumerate(sensors))

    server = Emulator()
    port = server.port
    events = []
    try:
        server.send(b"".join(frame(f) for f in range(10)))
        got = []
        with IgtlSource("127.0.0.1", port, retry_s=0.05, retries=400, frame_timeout_s=600) as source:
            read_until(source, 10, events, got)
            server.send(b"\x00\x02 not a header at all" + frame(10) + bytes(range(200)) + frame(11))
            read_until(source, 12, events, got)
            server.send(frame(12, names[:2]))  # frame 12 cut by the drop
            server.drop()
            wait_for_event(source, "reconnected", events)
            server.send(b"".join(frame(f) for f in range(13, 20)))
            read_until(source, 19, events, got)
            server.stop()  # the server restarts: a new process on the same port
            wait_for_event(source, "disconnected", events)
            server = Emulator(port)
            server.send(b"".join(frame(f) for f in range(20, 30)))
            read_until(source, 29, events, got)
    finally:
        server.stop()
    frames = [int(round((s.time - BASE) * 240)) for s in got]
    assert frames == [*range(0, 12), *range(13, 30)]
    assert all(s.valid.all() for s in got)
    kinds = {e.kind for e in events}
    assert {"garbage", "disconnected", "reconnected"} <= kinds
    assert any("dropped" in e.message for e in events if e.kind == "disconnected")
    position = np.array([s.position for s in got])
    assert np.allclose(position, p[frames] / 1000.0, atol=1e-7)


def test_retries_run_out_with_a_clear_error(server, rng):
    p, q = poses(rng, 3, 1)
    server.send(b"".join(transform("S0", BASE + f, p[f, 0], q[f, 0]) for f in range(3)))
    with IgtlSource("127.0.0.1", server.port, retries=3, retry_s=0.01) as source:
        read_until(source, 2)
        server.stop()
        with pytest.raises(LiveError, match="3 reconnection attempts"):
            deadline = time.monotonic() + DEADLINE_S
            while time.monotonic() < deadline:
                source.read(0.05)


def test_stale_tools_are_reported_within_half_a_second(server, rng):
    """A tool repeating its pose exactly, and one that stops arriving while the others stream, are stale within
    0.5 s of source time; when the whole stream stops, the host clock says so."""
    rate, frames = 240.0, 480
    p, q = poses(rng, frames, 3)
    p[100:, 1], q[100:, 1] = p[100, 1], q[100, 1]  # S1 repeats from frame 100
    data = b""
    for f in range(frames):
        for s, name in enumerate(["S0", "S1", "S2"]):
            if s == 2 and f >= 200:
                continue  # S2 stops arriving at frame 200
            data += transform(name, BASE + f / rate, p[f, s], q[f, s])
    server.send(data)
    events = []
    with IgtlSource("127.0.0.1", server.port, frame_timeout_s=0.05) as source:
        got = read_until(source, frames - 1, events)
        stale = {e.sensor: e.time for e in events if e.kind == "stale"}
        assert set(stale) == {1, 2}
        assert 0 < stale[1] - (BASE + 100 / rate) <= 0.5 + 1.5 / rate
        assert 0 < stale[2] - (BASE + 199 / rate) <= 0.5 + 1.5 / rate
        assert all(not s.valid[2] for s in got[200:])
        idle = wait_for_event(source, "stale", [])  # nothing more arrives: sensor 0 by the host clock
        assert [e.sensor for e in idle] == [0]


def test_registry_builds_the_source():
    source = open_live_source("igtl://127.0.0.1:18999", sensors=["a", "b"])
    assert isinstance(source, IgtlSource) and (source.host, source.port) == ("127.0.0.1", 18999)
    assert source.sensor_names == ("a", "b")


def test_time_going_back_is_a_reset_event_and_other_messages_are_ignored(server, rng):
    p, q = poses(rng, 8, 1)
    stamps = [BASE + 10 + f for f in range(4)] + [BASE + f for f in range(4)]  # a server restarted with its clock
    status = pack_message("STATUS", "S0", BASE, b"\0" * 30)
    server.send(b"".join(status + transform("S0", t, p[f, 0], q[f, 0]) for f, t in enumerate(stamps)))
    events = []
    with IgtlSource("127.0.0.1", server.port, frame_timeout_s=0.05) as source:
        got = read_until(source, 8, events)
    assert [s.time for s in got] == pytest.approx(stamps, abs=1e-6)
    assert [e.kind for e in events].count("reset") == 1
    assert sum("ignoring STATUS" in e.message for e in events) == 1
