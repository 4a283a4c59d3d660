"""The Polhemus serial source against the emulated tracker of tests/polhemus_emulator.py (a pseudo-terminal).

Every test waits on events (frame counts arriving, the emulator having written its last frame) with generous
deadlines as bounds only; none sleeps and then asserts."""

from __future__ import annotations

import os
import struct
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("serial")
if not hasattr(os, "openpty") or sys.platform == "win32":
    pytest.skip("pseudo-terminals are POSIX only", allow_module_level=True)

from ivc.collect.polhemus_serial import RECORD, PolhemusSource, parse_records, parse_stations  # noqa: E402
from ivc.collect.sources import open_live_source  # noqa: E402
from ivc.collect.stream import Sample, SourceEvent, StepRecorder  # noqa: E402
from ivc.errors import IvcError, LiveError  # noqa: E402
from tests.polhemus_emulator import BANNER, PolhemusEmulator, smooth_poses  # noqa: E402

DEADLINE_S = 60.0


def collect(source, emulator, frames: int | None = None):
    """Read until the emulator has written every frame and the source delivered them (or ``frames`` samples)."""
    samples, events = [], []
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        for item in source.read(0.1):
            (samples if isinstance(item, Sample) else events).append(item)
        wanted = frames if frames is not None else len(emulator.sent_frames())
        if (frames is not None or emulator.done.is_set()) and len(samples) >= wanted:
            return samples, events
    raise AssertionError(f"timed out: {len(samples)} samples, emulator sent {len(emulator.sent_frames())}")


def expected(emulator, positions, quaternions, hemisphere=(1.0, 0.0, 0.0), unit=0.01):
    """The truth of every frame the emulator streamed, as the binary format carries it (float32 in its unit)."""
    hemisphere = np.asarray(hemisphere)
    sent = emulator.sent_frames()
    truth = np.array([t for _, _, t in sent])
    p = positions[truth] / unit
    p = np.where((p @ hemisphere < 0)[..., None], -p, p)
    return sent, p.astype(np.float32).astype(float) * unit, quaternions[truth].astype(np.float32).astype(float)


def test_liberty_16_stations_every_frame_units_and_quaternions():
    positions, quaternions = smooth_poses(1500, 16, seed=1)
    with PolhemusEmulator(positions, quaternions, model="liberty", first_frame=5000) as emulator:
        with PolhemusSource(emulator.path) as source:
            assert source.sensor_names == tuple(str(s) for s in range(1, 17))
            assert source.sample_rate_hz == 240.0 and source.model == "liberty"
            samples, events = collect(source, emulator)
        sent, p, q = expected(emulator, positions, quaternions)
    # ivc configured the tracker itself: stop, binary, centimetres, hemisphere, output list, continuous
    assert emulator.commands[:6] == [b"P", b"F1", b"U1", b"H*,1,0,0", b"O*,2,7,9", b"C"]
    assert events and events[0].kind == "connected"
    frames = np.array([s.frame for s in samples])
    assert len(samples) == len(sent) == 1500
    np.testing.assert_array_equal(frames, [c for _, c, _ in sent])
    assert np.all(np.diff(frames) == 1)
    np.testing.assert_allclose([s.time for s in samples], frames / 240.0, rtol=0, atol=1e-9)
    position = np.stack([s.position for s in samples])
    quaternion = np.stack([s.quaternion for s in samples])
    np.testing.assert_allclose(position, p, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(quaternion, q, rtol=1e-12, atol=1e-15)
    # and against the truth itself, to the format's precision (float32 in cm)
    np.testing.assert_allclose(position, positions[:1500], rtol=0, atol=1e-7)
    assert all(s.valid.all() for s in samples)


def test_patriot_two_stations_at_60_hz_and_the_step_they_make():
    positions, quaternions = smooth_poses(300, 2, rate_hz=60.0, seed=2)
    with PolhemusEmulator(positions, quaternions, model="patriot", first_frame=77) as emulator:
        with open_live_source(f"polhemus:{emulator.path}") as source:
            assert isinstance(source, PolhemusSource)
            assert source.model == "patriot" and source.sample_rate_hz == 60.0
            samples, _ = collect(source, emulator)
        sent, p, q = expected(emulator, positions, quaternions)
    recorder = StepRecorder(2, source.sensor_names)
    for s in samples:
        recorder.add(s)
    step = recorder.to_step("check", sample_rate_hz=source.sample_rate_hz)
    assert step.n_frames == 300 and step.names == ["1", "2"]
    np.testing.assert_allclose(step.time, np.arange(300) / 60.0, atol=1e-9)
    np.testing.assert_allclose(step.position, p, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(step.quaternion, q, rtol=1e-12, atol=1e-15)


def test_dropouts_and_error_codes_are_invalid_samples_never_poses():
    positions, quaternions = smooth_poses(400, 4, seed=3)
    valid = np.ones((400, 4), bool)
    valid[100:110, 2] = False  # the truth's own dropouts
    errors = {(200, 1): ord("D"), (201, 1): ord("D"), (250, 3): 0x61}
    with PolhemusEmulator(positions, quaternions, valid, dropouts=[(300, 0)], errors=errors) as emulator:
        with PolhemusSource(emulator.path) as source:
            samples, events = collect(source, emulator)
    valid_seen = np.stack([s.valid for s in samples])
    bad = np.zeros((400, 4), bool)
    bad[100:110, 2] = bad[300, 0] = bad[200, 1] = bad[201, 1] = bad[250, 3] = True
    np.testing.assert_array_equal(valid_seen, ~bad)
    position = np.stack([s.position for s in samples])
    assert np.isnan(position[bad]).all() and not np.isnan(position[~bad]).any()
    said = " ".join(e.message for e in events if e.kind == "info")
    assert "'D'" in said and "'a'" in said


def test_repeated_frames_are_kept_once():
    positions, quaternions = smooth_poses(300, 3, seed=4)
    with PolhemusEmulator(positions, quaternions, repeat=[10, 11, 150, 299]) as emulator:
        with PolhemusSource(emulator.path) as source:
            samples, _ = collect(source, emulator)
            assert source.counts["repeated"] == 4 * 3
    frames = np.array([s.frame for s in samples])
    assert len(samples) == 300 and np.all(np.diff(frames) == 1)


def test_garbage_between_and_inside_the_stream_is_skipped_and_reported():
    positions, quaternions = smooth_poses(600, 5, seed=5)
    garbage = {50: b"\x00\xff noise \x13\x37", 51: b"L", 300: bytes(range(1, 60)), 599: b"\r\n#!"}
    with PolhemusEmulator(positions, quaternions, garbage=garbage) as emulator:
        with PolhemusSource(emulator.path) as source:
            samples, events = collect(source, emulator)
            assert source.counts["garbage_bytes"] == sum(len(g) for g in garbage.values())
    sent, p, _ = expected(emulator, positions, quaternions)
    assert len(samples) == len(sent) == 600
    assert np.all(np.diff([s.frame for s in samples]) == 1)
    np.testing.assert_allclose(np.stack([s.position for s in samples]), p, rtol=1e-12, atol=1e-15)
    assert any(e.kind == "garbage" for e in events)


def test_a_reset_mid_stream_is_survived_reported_and_the_time_line_continues():
    positions, quaternions = smooth_poses(900, 4, seed=6)
    with PolhemusEmulator(positions, quaternions, reset_at=400, first_frame=9000) as emulator:
        with PolhemusSource(emulator.path, stall_s=0.3) as source:
            samples, events = collect(source, emulator)
            assert source.counts["resets"] >= 1
        sent, p, q = expected(emulator, positions, quaternions)
    assert emulator.epoch == 1 and emulator.commands.count(b"O*,2,7,9") == 2  # configured again after the reset
    assert len(samples) == len(sent) == 900
    assert [s.frame for s in samples] == [c for _, c, _ in sent]  # 9000.. then 0.. after the reset
    times = np.array([s.time for s in samples])
    assert np.all(np.diff(times) > 0)
    np.testing.assert_allclose(np.diff(times[:400]), 1 / 240.0, atol=1e-9)
    np.testing.assert_allclose(np.diff(times[400:]), 1 / 240.0, atol=1e-9)
    np.testing.assert_allclose(np.stack([s.position for s in samples]), p, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.stack([s.quaternion for s in samples]), q, rtol=1e-12, atol=1e-15)
    resets = [e for e in events if e.kind == "reset"]
    assert resets and "configured again" in resets[0].message
    assert any(e.kind == "garbage" for e in events)  # the reboot's text line
    assert BANNER  # the emulator printed it


def test_a_stalled_line_is_configured_again_without_losing_a_frame_or_the_time_line():
    positions, quaternions = smooth_poses(600, 3, seed=10)
    with PolhemusEmulator(positions, quaternions, pauses={300: 0.6}) as emulator:
        with PolhemusSource(emulator.path, stall_s=0.2) as source:
            samples, events = collect(source, emulator)
        sent, p, _ = expected(emulator, positions, quaternions)
    assert emulator.commands.count(b"C") >= 2 and any(e.kind == "reset" for e in events)
    frames = np.array([s.frame for s in samples])
    np.testing.assert_array_equal(frames, [c for _, c, _ in sent])  # every frame sent, the stalled ones never were
    assert frames[300] - frames[299] > 1
    np.testing.assert_allclose([s.time for s in samples], frames / 240.0, rtol=0, atol=1e-9)  # one time line
    np.testing.assert_allclose(np.stack([s.position for s in samples]), p, rtol=1e-12, atol=1e-15)


def test_a_counter_restart_without_silence_is_a_reset_too():
    """Frame counts far behind the last are a new time line, never repeats or a negative time step."""
    source = PolhemusSource("/dev/null-polhemus")
    source.sample_rate_hz = 240.0
    source.stations = [1]
    source._lookup[1] = 0
    records = np.zeros(6, RECORD)
    records["preamble"], records["station"], records["command"] = b"LY", 1, ord("C")
    records["size"] = RECORD.itemsize - 8
    records["position"] = (30.0, 1.0, 2.0)
    records["quaternion"] = (1.0, 0.0, 0.0, 0.0)
    records["frame"] = [500, 501, 502, 3, 4, 5]
    out = source._frames(records, final=True)
    samples = [o for o in out if isinstance(o, Sample)]
    resets = [o for o in out if isinstance(o, SourceEvent) and o.kind == "reset"]
    assert [s.frame for s in samples] == [500, 501, 502, 3, 4, 5] and len(resets) == 1
    assert np.all(np.diff([s.time for s in samples]) > 0)


def test_sensors_select_and_order_stations_and_hemisphere_is_sent():
    positions, quaternions = smooth_poses(200, 4, seed=7)
    positions = positions * np.array([-1.0, 1.0, 1.0])  # sensors in the -x hemisphere
    with PolhemusEmulator(positions, quaternions) as emulator:
        with PolhemusSource(emulator.path, sensors=["3", "1"], hemisphere="-x") as source:
            assert source.sensor_names == ("3", "1")
            samples, _ = collect(source, emulator)
        sent, p, _ = expected(emulator, positions, quaternions, hemisphere=np.array([-1.0, 0.0, 0.0]))
    assert b"H*,-1,0,0" in emulator.commands
    np.testing.assert_allclose(np.stack([s.position for s in samples]), p[:, [2, 0]], rtol=1e-12, atol=1e-15)
    with PolhemusEmulator(positions, quaternions) as emulator:
        with pytest.raises(LiveError, match=r"station\(s\) \[7\].*streams stations \[1, 2, 3, 4\]"):
            PolhemusSource(emulator.path, sensors=["1", "7"], hemisphere="-x").open()


def test_a_vanished_port_is_retried_then_reported_with_what_to_do():
    positions, quaternions = smooth_poses(2000, 2, seed=8)
    pulled = threading.Event()
    with PolhemusEmulator(positions, quaternions, close_at=500, close_when=pulled) as emulator:
        source = PolhemusSource(emulator.path, retries=2, retry_wait_s=0.05)
        source.open()
        samples, events = collect(source, emulator, frames=500)
        pulled.set()  # the cable is pulled once the first 500 frames are in
        with pytest.raises(LiveError, match="could not be reopened in 2 tries.*reconnect the tracker") as raised:
            deadline = time.monotonic() + DEADLINE_S
            while time.monotonic() < deadline:
                for item in source.read(0.1):
                    (samples if isinstance(item, Sample) else events).append(item)
        assert isinstance(raised.value, IvcError)
        assert emulator.closed.is_set()
        source.close()
    assert len(samples) == 500  # every frame before the loss was delivered
    assert any(e.kind == "disconnected" for e in events) and source.counts["reconnects"] == 0


def test_a_tracker_that_stays_silent_is_configured_again_then_refused():
    positions, quaternions = smooth_poses(300, 2, seed=9)
    with PolhemusEmulator(positions, quaternions) as emulator:
        source = PolhemusSource(emulator.path, stall_s=0.2, reconfigure_limit=2)
        source.open()
        samples, events = [], []
        with pytest.raises(LiveError, match="sent no frame for .* despite 2 re-configurations: check"):
            deadline = time.monotonic() + DEADLINE_S
            while time.monotonic() < deadline:
                for item in source.read(0.1):
                    (samples if isinstance(item, Sample) else events).append(item)
        source.close()
    assert len(samples) == 300
    assert [e.kind for e in events].count("reset") == 2
    assert emulator.commands.count(b"C") == 3


def test_a_port_that_does_not_exist_is_refused_clearly():
    with pytest.raises(LiveError, match="cannot open the Polhemus serial port /dev/no-such-tty.*dialout"):
        PolhemusSource("/dev/no-such-tty").open()


def test_a_silent_tracker_is_refused_with_what_to_check():
    positions, quaternions = smooth_poses(10, 1)
    with PolhemusEmulator(positions, quaternions, max_frames=0) as emulator:
        with pytest.raises(LiveError, match="no frame from the Polhemus tracker.*switched on"):
            PolhemusSource(emulator.path, open_timeout_s=0.5).open()


@pytest.mark.parametrize("kwargs, match", [
    ({"sensors": ["a"]}, "not a station number"),
    ({"sensors": ["0"]}, "not a station number"),
    ({"sensors": ["17"]}, "not a station number"),
    ({"sensors": ["1", "1"]}, "twice"),
    ({"sensors": []}, "names no station"),
    ({"hemisphere": "x"}, "hemisphere"),
    ({"model": "fastrak"}, "model"),
    ({"rate_hz": 0}, "rate_hz"),
    ({"rate_hz": "fast"}, "rate_hz"),
    ({"baudrate": -1}, "baudrate"),
    ({"retries": -1}, "retries"),
    ({"retries": 1.5}, "retries"),
    ({"reconfigure_limit": 0}, "reconfigure_limit"),
])
def test_bad_arguments_are_refused(kwargs, match):
    with pytest.raises(LiveError, match=match):
        PolhemusSource("/dev/ttyUSB0", **kwargs)


def test_the_registry_builds_the_source_and_refuses_an_empty_device():
    source = open_live_source("polhemus:/dev/ttyUSB9", sensors=["2", "1"], hemisphere="+z")
    assert isinstance(source, PolhemusSource) and source.port == "/dev/ttyUSB9" and source.hemisphere == "+z"
    assert parse_stations(["2", "1"]) == [2, 1] and parse_stations(None) is None
    with pytest.raises(LiveError):
        open_live_source("polhemus:")
    with pytest.raises(LiveError, match="open the Polhemus source"):
        source.read(0.01)


def _record(station, frame, position=(10.0, 0.0, 0.0), error=0, preamble=b"LY"):
    return (preamble + bytes([station, ord("C"), error, 0]) + struct.pack("<h", 32)
            + struct.pack("<3f4fI", *position, 1.0, 0.0, 0.0, 0.0, frame))


def test_parser_resynchronises_on_headers_at_any_split_point():
    """Records with garbage between them, cut at every possible point, parse to the same records."""
    rng = np.random.default_rng(0)
    clean = [_record(s, f, (f, s, 1.0)) for f in range(20) for s in (1, 2)]
    noise = [b"", b"xx", b"\x00" * 7, b"L", b"LYx", b"P", b"\xff\xfe junk"]
    response = b"LY" + bytes([0, ord("O"), 3, 0]) + struct.pack("<h", 17) + b"invalid parameter"
    stream = b"".join(r + noise[rng.integers(len(noise))] + (response if n == 5 else b"")
                      for n, r in enumerate(clean))
    for cut in range(0, len(stream), 7):
        first, _, junk1, used = parse_records(stream[:cut], [b"LY", b"PA"])
        rest, responses, junk2, used2 = parse_records(stream[used:], [b"LY", b"PA"])
        records = np.concatenate([first, rest])
        assert len(records) == 40, cut
        np.testing.assert_array_equal(records["frame"], np.repeat(np.arange(20), 2))
        np.testing.assert_array_equal(records["station"], np.tile([1, 2], 20))
        np.testing.assert_array_equal(records["position"][:, 0], np.repeat(np.arange(20), 2))
        assert used + used2 == len(stream) or stream[used + used2:] in (b"L", b"P")


def test_parser_decodes_many_records_in_one_pass():
    """A megabyte of records is one numpy view (no per-record Python): a loose bound on the speed."""
    block = b"".join(_record(1 + s, f) for f in range(1000) for s in range(16))
    records, responses, garbage, used = parse_records(block * 2, [b"LY"])
    assert len(records) == 32000 and not responses and garbage == 0 and used == len(block) * 2
