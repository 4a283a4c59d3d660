"""`--live` on a cold compile cache: it connects at once, corrects with the interpreted kernels while the compiled
ones build in a background thread, then switches, with the same results throughout."""

import socket
import threading
import time

import numpy as np
import pytest
from pyigtl import TransformMessage

from ivc import compiled, rotations
from ivc.correct import Corrector, PoseCorrector, pose_kernels
from ivc.live import LiveCorrector
from ivc.live.igtl import Framer
from tests.helpers import distorted, reported_matrices

SENSORS = ("S0", "S1", "S2", "S3")


def reported_poses(rng, frames):
    """Reported poses (F, N, 4, 4), mm, float32, of len(SENSORS) sensors at random distorted poses."""
    S = distorted(rng, frames * len(SENSORS))[2]
    return reported_matrices(S).reshape(frames, len(SENSORS), 4, 4)


def offline(table, matrices):
    """``ivc correct`` on the same poses: batch, each sample on its own, through the pose path."""
    m = matrices.astype(float)
    return PoseCorrector(table).batch(m[..., :3, 3] / 1000.0, rotations.from_matrix(m[..., :3, :3]))


def _received(consumer, framer, count, deadline):
    """``count`` corrected TRANSFORMs from the publish socket: {(device, timestamp): matrix}."""
    out = {}
    while len(out) < count and time.monotonic() < deadline:
        framer.feed(consumer.recv(1 << 16))
        for f in framer.messages():
            if f.message_type == "TRANSFORM":
                out[(f.device_name, round(f.timestamp, 6))] = f.payload
    return out


@pytest.mark.slow  # the whole live loop on interpreted kernels (its seed map built by NumPy): ~14 s
def test_live_connects_at_once_on_a_cold_cache_and_switches_to_compiled(exact_table, rng, monkeypatch):
    ready, go = threading.Event(), threading.Event()
    monkeypatch.setattr(compiled, "SMALL", 64)
    monkeypatch.setattr(compiled, "is_ready", lambda kernel: ready.is_set())  # a fresh install's cache
    compiled.used.clear()
    warm_up = LiveCorrector._warm_up

    def slow_compile(corrector, pose_corrector):  # a compilation that lasts until the test says so
        if threading.current_thread().name == "ivc-compile":
            go.wait(120)  # a bound, not a wait: the test sets it once the interpreted frames have arrived
            warm_up(corrector, pose_corrector)
            ready.set()
        else:
            warm_up(corrector, pose_corrector)

    monkeypatch.setattr(LiveCorrector, "_warm_up", staticmethod(slow_compile))
    matrices = reported_poses(rng, 8)
    expected = offline(exact_table, matrices)
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(10)
    live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0))
    assert live.compiling
    stop = threading.Event()
    runner = threading.Thread(target=live.run, kwargs={"stop": stop})
    start = time.monotonic()
    runner.start()
    upstream, _ = listener.accept()
    assert time.monotonic() - start < 5 and live.compiling  # connected while the kernels still compile
    consumer = socket.create_connection(live.publish_address)
    consumer.settimeout(60)  # the first frame builds the pose path's seed map with the NumPy forms: seconds
    framer = Framer()
    got = {}
    try:
        time.sleep(0.3)

        def send(frames):
            for k in frames:
                for n, name in enumerate(SENSORS):
                    upstream.sendall(TransformMessage(matrices[k, n], timestamp=1000.0 + k / 240,
                                                      device_name=name).pack())

        send(range(4))
        got.update(_received(consumer, framer, 4 * len(SENSORS), time.monotonic() + 60))
        assert live.compiling and compiled.name_of(pose_kernels.invert_serial) in compiled.used
        go.set()
        deadline = time.monotonic() + 120
        while live.compiled_after_s is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert live.compiled_after_s is not None and not live.compiling
        compiled.used.clear()
        send(range(4, 8))
        got.update(_received(consumer, framer, 4 * len(SENSORS), time.monotonic() + 60))
        assert compiled.name_of(pose_kernels.invert_serial) not in compiled.used  # compiled from now on
    finally:
        go.set()
        stop.set()
        runner.join(30)
        for s in (upstream, consumer, listener):
            s.close()
    assert len(got) == 8 * len(SENSORS) and live.stats.flagged == np.count_nonzero(expected.flags)
    for k in range(8):
        for n, name in enumerate(SENSORS):
            matrix = got[(f"{name}_ivc", round(1000.0 + k / 240, 6))]
            assert np.allclose(matrix[:3, 3] / 1000.0, expected.position[k, n], atol=2e-6)
            q = rotations.from_matrix(np.asarray(matrix[:3, :3], float))
            assert rotations.angle_between(q, expected.quaternion[k, n]) < 2e-5


def test_no_background_compilation_when_the_kernels_are_cached(exact_table):
    listener = socket.create_server(("127.0.0.1", 0))
    try:
        live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0))
        assert not live.compiling and live.compiled_after_s is None
        live.close()
    finally:
        listener.close()
