"""Live correction over OpenIGTLink on loopback: pyigtl peers on both sides, against offline correction."""

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from pyigtl import OpenIGTLinkClient, OpenIGTLinkServer, StringMessage, TransformMessage

from ivc import dipole, rotations
from ivc.correct import Corrector
from ivc.correct.reported import PoseCorrector
from ivc.live import LiveCorrector, NDArrayMessage, TrackingDataMessage
from ivc.live.igtl import Framer
from ivc.lut import write as write_lut
from tests.helpers import distorted, reported_matrices

SENSORS = ("S0", "S1", "S2", "S3")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def reported_poses(rng, frames):
    """Reported poses (F, N, 4, 4) of len(SENSORS) sensors at random distorted poses."""
    r, T, S = distorted(rng, frames * len(SENSORS))
    return reported_matrices(S).reshape(frames, len(SENSORS), 4, 4)


def offline(table_or_corrector, matrices):
    """``ivc correct`` on the same (float32) poses: batch, each sample on its own, through the pose path."""
    table = table_or_corrector.field if isinstance(table_or_corrector, Corrector) else table_or_corrector
    m = matrices.astype(float)
    return PoseCorrector(table).batch(m[..., :3, 3] / 1000.0, rotations.from_matrix(m[..., :3, :3]))


def test_framer_resynchronises_after_garbage_and_checks_the_crc():
    good = TransformMessage(np.eye(4), device_name="S0").pack()
    corrupt = bytearray(good)
    corrupt[-1] ^= 0xFF  # body no longer matches its CRC
    framer = Framer()
    framer.feed(b"\x00\x02garbage that looks a little like a header" + bytes(corrupt) + good[:30])
    assert framer.messages() == []
    framer.feed(good[30:] + NDArrayMessage(np.arange(9.0).reshape(3, 3), device_name="S1").pack())
    frames = framer.messages()
    assert [(f.message_type, f.device_name) for f in frames] == [("TRANSFORM", "S0"), ("NDARRAY", "S1")]
    assert np.array_equal(frames[1].payload, np.arange(9.0).reshape(3, 3))
    assert framer.garbage > 0 and not framer.buffer


def test_tdata_round_trip():
    tools = {"S0": np.diag([1.0, -1.0, -1.0, 1.0]), "S1": np.eye(4)}
    tools["S1"][:3, 3] = [10.0, -20.0, 30.5]
    framer = Framer()
    framer.feed(TrackingDataMessage(tools, device_name="ivc").pack())
    (frame,) = framer.messages()
    assert frame.message_type == "TDATA"
    message = TrackingDataMessage()
    message._unpack_content(TrackingDataMessage(tools).pack()[58:])
    assert all(np.allclose(message.tools[k], tools[k]) for k in tools)


def _collect(client, frames_expected, timeout=60.0):
    """Corrected matrices received by a pyigtl client, sensor by sensor. ``timeout`` (s) bounds the wait for an
    event, not a timing: the first frame may wait on ``ivc correct --live`` compiling its kernels on a loaded
    machine (10 s was missed once, in CI beside a cold ``ivc demo``)."""
    out = []
    for name in SENSORS:
        message = client.wait_for_message(name + "_ivc", timeout=timeout)
        assert message is not None, f"no corrected pose for {name}"
        out.append((message.matrix, message.metadata, message.timestamp))
    return out


@pytest.mark.slow
def test_ivc_correct_live_matches_offline_and_survives_a_server_restart(exact_table, rng, tmp_path):  # noqa: F811
    lut_path = tmp_path / "map.h5"
    write_lut(exact_table, lut_path)
    matrices = reported_poses(rng, 24)
    expected = offline(exact_table, matrices)
    source_port, publish_port = free_port(), free_port()
    server = OpenIGTLinkServer(port=source_port, local_server=True)
    process = subprocess.Popen([sys.executable, "-m", "ivc.cli", "correct", str(lut_path), "--live",
                                f"igtl://127.0.0.1:{source_port}", "--publish", f"127.0.0.1:{publish_port}"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=dict(os.environ, PYTHONUNBUFFERED="1"))
    client = None
    try:
        deadline = time.monotonic() + 60
        while not server.is_connected():
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "ivc never connected"
            time.sleep(0.05)
        client = OpenIGTLinkClient(host="127.0.0.1", port=publish_port)
        while not client.is_connected():
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.2)

        def stream(server, frames):
            got = []
            for k in frames:
                for n, name in enumerate(SENSORS):
                    server.send_message(TransformMessage(matrices[k, n], timestamp=1000.0 + k / 240,
                                                         device_name=name), wait=False)
                got.append(_collect(client, 1))
            return got

        first = stream(server, range(12))
        server.stop()  # the tracking server goes away ...
        time.sleep(1.0)
        server = OpenIGTLinkServer(port=source_port, local_server=True)  # ... and comes back
        deadline = time.monotonic() + 20
        while not server.is_connected():
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "ivc did not reconnect"
            time.sleep(0.05)
        second = stream(server, range(12, 24))
        received = first + second
        for k, frame in enumerate(received):
            for n, (matrix, metadata, stamp) in enumerate(frame):
                assert stamp == pytest.approx(1000.0 + k / 240, abs=1e-6)
                assert int(metadata["ivc_flags"]) == expected.flags[k, n]
                assert np.allclose(matrix[:3, 3] / 1000.0, expected.position[k, n], atol=2e-6)
                q = rotations.from_matrix(np.asarray(matrix[:3, :3], float))
                assert rotations.angle_between(q, expected.quaternion[k, n]) < 2e-5
    finally:
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=30)
        if client is not None:
            client.stop()
        server.stop()
    assert "connections 2" in err, err
    assert "Traceback" not in err, err


@pytest.mark.slow
def test_bad_input_is_dropped_and_logged_once_and_slow_clients_do_not_block(exact_table, rng, caplog):  # noqa: F811
    """Garbage bytes, other message types, unknown sensors, out-of-order stamps and NaN poses on a raw socket."""
    matrices = reported_poses(rng, 6)
    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0), sensors=list(SENSORS))
    stop = threading.Event()
    runner = threading.Thread(target=live.run, kwargs={"stop": stop})
    runner.start()
    upstream, _ = listener.accept()
    consumer = socket.create_connection(live.publish_address)
    idle = socket.create_connection(live.publish_address)  # connects and never reads
    try:
        def send(k, name, m, stamp=None):
            upstream.sendall(TransformMessage(m, timestamp=1000.0 + k / 240 if stamp is None else stamp,
                                              device_name=name).pack())

        upstream.sendall(os.urandom(3000))
        upstream.sendall(StringMessage("hello", device_name="S0").pack())
        for k in range(6):
            for n, name in enumerate(SENSORS):
                send(k, name, matrices[k, n])
            send(k, "Needle", matrices[k, 0])  # not in --sensor
        send(2, "S0", matrices[2, 0])  # repeated (out of order) timestamp
        nan = matrices[0, 0].copy()
        nan[0, 3] = np.nan
        send(10, "S1", nan)
        upstream.sendall(os.urandom(500))
        send(11, "S2", matrices[5, 2])
        framer = Framer()
        consumer.settimeout(30.0)  # a bound on waiting, not a timing
        names = []
        deadline = time.monotonic() + 20
        while names.count("S2_ivc") < 7 and time.monotonic() < deadline:
            framer.feed(consumer.recv(1 << 16))
            names += [f.device_name for f in framer.messages() if f.message_type == "TRANSFORM"]
    finally:
        stop.set()
        runner.join(10)
        for s in (upstream, consumer, idle, listener):
            s.close()
    stats = live.stats
    assert names.count("S0_ivc") == 6 and names.count("S2_ivc") == 7 and "Needle_ivc" not in names
    assert stats.unknown == 6 and stats.out_of_order == 1 and stats.garbage_bytes >= 3000
    assert stats.received == 6 * 4 + 1 and stats.rejected == 1  # the NaN pose is dropped, logged, not published
    assert stats.flagged == 0  # TRANSFORMs go through the pose path: every valid pose of the exact table is trusted
    warnings = [r.getMessage() for r in caplog.records]
    assert sum("unknown sensor 'Needle'" in w for w in warnings) == 1
    assert sum("malformed bytes" in w for w in warnings) == 1
    assert sum("'S1': dropped a TRANSFORM message: it holds NaN" in w for w in warnings) == 1


@pytest.mark.slow
def test_live_prediction_matches_offline_correct_then_predict(exact_table, rng):  # noqa: F811
    """`--predict`: each sensor's corrected orientation predicted 50 ms ahead, as `ivc correct --predict` offline."""
    from ivc.predict import make
    from tests.helpers import quadratic_field

    frames, rate, horizon = 60, 240.0, 0.05
    r = np.broadcast_to(exact_table.grid.nodes()[10, 10, 10] + [[0.05, 0.02, -0.03], [-0.04, 0.06, 0.01]],
                        (frames, 2, 3))  # two sensors held still, turning at constant rates
    t = np.arange(frames) / rate
    omega = np.array([[0.8, -1.5, 2.0], [-2.5, 0.4, 1.1]])  # rad/s
    q = rotations.multiply(rotations.from_rotvec(t[:, None, None] * omega), rotations.random(2, rng))
    S = dipole.signal(r, rotations.to_matrix(q), quadratic_field(r.reshape(-1, 3)).reshape(frames, 2, 3, 3))
    matrices = reported_matrices(S)
    # TRANSFORM input goes through the pose path on both sides (max_residual gates signal input only)
    corrected = offline(Corrector(exact_table, max_residual=1.0), matrices)
    assert np.all(corrected.flags == 0)
    expected = make("dqekf-cv", rate).predict(corrected.quaternion, horizon, corrected.flags == 0)[0]

    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(exact_table, max_residual=1.0), listener.getsockname(), ("127.0.0.1", 0),
                         predictor="dqekf-cv",
                         horizon=horizon, rate_hz=rate)
    stop = threading.Event()
    runner = threading.Thread(target=live.run, kwargs={"stop": stop})
    runner.start()
    upstream, _ = listener.accept()
    consumer = socket.create_connection(live.publish_address)
    received = {}
    try:
        time.sleep(0.2)
        for k in range(frames):
            upstream.sendall(b"".join(TransformMessage(matrices[k, n], timestamp=1000.0 + k / rate,
                                                       device_name=f"S{n}").pack() for n in range(2)))
        framer = Framer()
        consumer.settimeout(30.0)  # a bound on waiting, not a timing
        deadline = time.monotonic() + 20
        while len(received) < 2 * frames and time.monotonic() < deadline:
            framer.feed(consumer.recv(1 << 16))
            for f in framer.messages():
                if f.message_type == "TRANSFORM":
                    received[f.device_name, round((f.timestamp - 1000.0) * rate)] = f
    finally:
        stop.set()
        runner.join(10)
        for s in (upstream, consumer, listener):
            s.close()
    assert len(received) == 2 * frames
    predicted_frames = 0
    for (device, k), frame in received.items():
        n = int(device[1])
        got = rotations.from_matrix(np.asarray(frame.payload[:3, :3], float))
        if np.all(np.isfinite(expected[k, n])):
            predicted_frames += 1
            assert rotations.angle_between(got, expected[k, n]) < 5e-5, (device, k)
        else:  # no prediction yet: the corrected orientation itself
            assert rotations.angle_between(got, corrected.quaternion[k, n]) < 2e-5
    assert predicted_frames >= 2 * (frames - 3)
    # the prediction really looks ahead: 50 ms of rotation, not the measured orientation
    ahead = rotations.angle_between(expected[-1], corrected.quaternion[-1])
    assert np.allclose(ahead, np.linalg.norm(omega, axis=1) * horizon, rtol=0.05)


@pytest.mark.slow
def test_live_prediction_takes_the_tuning(exact_table):  # noqa: F811
    """--tune-from reaches each sensor's filter; a tuning made at another rate is refused before any socket opens."""
    from ivc.predict import PredictorError, Tuning, make

    tuning = Tuning(240.0, 1 / 120, 0, np.full(4, 1e-4), np.array([1e-7, 1e-4, 5e-5, 5e-5]), ())
    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0), predictor="mmdq2",
                         rate_hz=240.0, tuning=tuning)
    try:
        live._predicted("S0", np.array([1.0, 0.0, 0.0, 0.0]), True)
        got, want = live._streams["S0"].predictor._config, make("mmdq2", 240.0, tuning)._config
        assert all(np.allclose(a, b) for a, b in zip(got, want, strict=True))
        assert not np.allclose(got[2], make("mmdq2", 240.0)._config[2])
        with pytest.raises(PredictorError, match="tuning is for 240 Hz"):
            LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0), predictor="mmdq2",
                          rate_hz=120.0, tuning=tuning)
    finally:
        live.close()
        listener.close()


def test_live_prediction_runs_on_the_time_stamps_and_auto_scores_at_the_horizon(exact_table, rng):  # noqa: F811
    """Jittered stamps reach the predictor (as the batch with those times); auto and direct learn at --horizon."""
    from ivc.predict import make
    from ivc.predict.delta import delta_q

    n, rate, horizon = 240, 60.0, 0.08
    t = 1000.0 + np.cumsum(rng.uniform(0.010, 0.025, n))
    w = np.stack([1.5 * np.sin(2 * np.pi * 0.7 * (t - 1000.0)), 0.4 + 0 * t, 0.6 * np.cos(2 * np.pi * 0.3 * t)], 1)
    q = np.empty((n, 4))
    q[0] = rotations.random(1, rng)[0]
    for k in range(1, n):
        q[k] = rotations.multiply(delta_q(w[k] * (t[k] - t[k - 1]), 1.0), q[k - 1])
    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0), predictor="auto",
                         horizon=horizon, rate_hz=rate)
    try:
        got = np.array([live._predicted("S0", q[k], True, t[k]) for k in range(n)])
        stream = live._streams["S0"]
        assert stream.predictor.horizon_s == horizon
        assert [p.horizon_s for p in stream.predictor.bank if p.name == "direct"] == [horizon]
    finally:
        live.close()
        listener.close()
    batch = make("auto", rate).predict(q, [horizon], time=t)[0]  # batch weights are per horizon
    assert np.max(rotations.angle_between(got[20:], batch[20:])) < 1e-9
