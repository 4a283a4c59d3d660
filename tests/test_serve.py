"""``ivc serve``: a session (the simulated protocol, a replay) served over OpenIGTLink as PLUS serves a tracker, read
back through the igtl:// source pose for pose, corrected by ``ivc correct --live``; clients that leave; Ctrl-C."""

import importlib.util
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from ivc import rotations
from ivc.app.serve import IgtlServer, serve_source
from ivc.collect.igtl import IgtlSource
from ivc.collect.stream import Sample, SessionSource, StepRecorder
from ivc.correct import Corrector
from ivc.correct.reported import PoseCorrector
from ivc.errors import LiveError
from ivc.live import LiveCorrector
from ivc.session import Session, Step
from ivc.session import write as write_session
from tests.helpers import distorted, reported_matrices

DEADLINE_S = 60.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(server: IgtlServer) -> threading.Thread:
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    return thread


def record(source: IgtlSource, total: int) -> dict[str, StepRecorder]:
    """Every frame of ``source`` into one recorder per Sample.step, until ``total`` frames (events waited on)."""
    recorders: dict[str, StepRecorder] = {}
    count = 0
    deadline = time.monotonic() + DEADLINE_S
    while count < total:
        assert time.monotonic() < deadline, f"only {count} of {total} frames arrived"
        for item in source.read(0.2):
            if isinstance(item, Sample):
                names = source.names_by_step.get(item.step, source.sensor_names)
                recorder = recorders.setdefault(item.step, StepRecorder(item.n_sensors, names))
                recorder.add(item)
                count += 1
    return recorders


def pose_session(rng, frames=(30, 20), sensors=(3, 2), invalid=0.1) -> Session:
    """Steps of tracker poses (F, N) in the distorted ball, a share ``invalid`` of the samples invalid."""
    session = Session(hemisphere="+x")
    for name, f, n in zip(("wand_sweep", "check")[:len(frames)], frames, sensors, strict=True):
        m = reported_matrices(distorted(rng, f * n)[2]).astype(float).reshape(f, n, 4, 4)
        valid = rng.random((f, n)) >= invalid
        position = np.where(valid[..., None], m[..., :3, 3] / 1000.0, np.nan)
        quaternion = np.where(valid[..., None], rotations.from_matrix(m[..., :3, :3]), np.nan)
        session.steps[name] = Step(time=np.arange(f) / 240.0, position=position, quaternion=quaternion, valid=valid,
                                   sensor_ids=[f"{name[:4]}{i}" for i in range(n)])
    return session


def assert_same_step(got: Step, want: Step, signals: bool) -> None:
    assert got.n_frames == want.n_frames and got.n_sensors == want.n_sensors
    assert np.array_equal(got.valid_mask, want.valid_mask)
    ok = want.valid_mask
    assert np.abs(got.position[ok] - want.position[ok]).max() <= 1e-6  # metres: pose for pose
    dot = np.abs(np.sum(got.quaternion[ok] * want.quaternion[ok], axis=-1))
    assert np.all(dot >= 1 - 1e-10)  # the same rotation (q and -q alike)
    assert np.isnan(got.position[~ok]).all()
    assert np.allclose(got.time, want.time - want.time[0], atol=1e-6)
    if signals:
        assert np.array_equal(got.signal[ok], want.signal[ok])
    else:
        assert got.signal is None


@pytest.fixture(scope="module")
def rehearsal():
    """``ivc serve sim``'s source: the simulator running the protocol (a few frames a step), as fast as read."""
    from ivc.sim import Simulator, load_scene

    steps = Simulator(load_scene("default"), 7).steps
    return serve_source("sim:default", seed=7, pause_s=0.5, speed=float("inf"), frames={n: 12 for n in steps})


@pytest.mark.slow
@pytest.mark.parametrize("signals", [True, False], ids=["with-signals", "poses-only"])
def test_served_simulation_recorded_through_igtl_is_the_same_session(rehearsal, signals):
    """The simulated protocol served, read by the igtl:// source and recorded per step gives the simulator's
    session pose for pose (1e-6 m), valid flags, times and (with signals) signal matrices; as a PLUS user gets it,
    without signals."""
    session = rehearsal.session
    source = SessionSource(session, pause_s=0.5)
    server = IgtlServer(source, 0, lossless=True, start_on_connect=True, signals=signals)
    thread = start(server)
    with IgtlSource(*server.address) as client:
        recorders = record(client, len(source))
    thread.join(DEADLINE_S)
    assert list(recorders) == list(session.steps)
    for name, recorder in recorders.items():
        want = session.steps[name]
        got = recorder.to_step(name)
        assert [n.removesuffix("ToTracker") for n in got.names] == want.names
        assert_same_step(got, want, signals)


def test_several_clients_and_one_that_leaves(rng):
    """Two clients of a real-time stream; the first leaves, the second receives every later frame as served."""
    session = pose_session(rng, frames=(480,), sensors=(3,))
    step = session.steps["wand_sweep"]
    source = SessionSource(session, realtime=True)
    server = IgtlServer(source, 0, start_on_connect=True, signals=False)
    thread = start(server)
    leaving = IgtlSource(*server.address)
    leaving.open()
    staying = IgtlSource(*server.address, retries=1)
    staying.open()
    leaving.close()  # the server goes on
    got = []
    with pytest.raises(LiveError, match="reconnection attempts"):  # the stream ends: the server closes
        deadline = time.monotonic() + DEADLINE_S
        while time.monotonic() < deadline:
            got += [s for s in staying.read(0.2) if isinstance(s, Sample)]
    thread.join(DEADLINE_S)
    assert not thread.is_alive() and server.stats.clients == 2 and server.stats.frames == len(source)
    first = int(round((got[0].time - server.epoch) * 240))
    assert len(got) == step.n_frames - first > 240  # every frame since it connected
    ok = step.valid_mask[first:]
    assert np.array_equal([s.valid for s in got], ok)
    assert np.abs(np.array([s.position for s in got])[ok] - step.position[first:][ok]).max() <= 1e-6


def test_ivc_correct_live_corrects_what_ivc_serve_serves(rng, exact_table):
    """The live loop, connected to the server, publishes each served pose corrected as offline correction does."""
    session = pose_session(rng, frames=(40,), sensors=(3,), invalid=0.0)  # the loop reads no PLUS status
    step = session.steps["wand_sweep"]
    names = [f"{n}ToTracker" for n in step.names]
    served = IgtlServer(SessionSource(session, chunk=8), 0, lossless=True, start_on_connect=True, signals=False)
    loop = LiveCorrector(Corrector(exact_table), served.address, ("127.0.0.1", 0), background_compile=False)
    stop = threading.Event()
    loop_thread = threading.Thread(target=loop.run, kwargs={"stop": stop}, daemon=True)
    with IgtlSource(*loop.publish_address, sensors=[f"{n}_ivc" for n in names], stale_after_s=60) as corrected:
        loop_thread.start()
        server_thread = start(served)
        deadline = time.monotonic() + DEADLINE_S
        got = []
        while len(got) < step.n_frames:
            assert time.monotonic() < deadline, f"{len(got)} corrected frames of {step.n_frames}"
            got += [s for s in corrected.read(0.2) if isinstance(s, Sample)]
    stop.set()
    loop_thread.join(DEADLINE_S)
    server_thread.join(DEADLINE_S)
    want = PoseCorrector(exact_table).batch(step.position, step.quaternion)
    ok = step.valid_mask
    position = np.array([s.position for s in got])
    assert np.array([s.valid for s in got]).all()
    assert np.abs(position[ok] - want.position[ok]).max() < 1e-5
    assert loop.stats.corrected + loop.stats.flagged == ok.sum()


def test_ivc_serve_command_streams_a_replay_and_stops_on_ctrl_c(rng, tmp_path):
    session = pose_session(rng, frames=(2400, 10))
    path = tmp_path / "session.h5"
    write_session(session, path)
    port = free_port()
    process = subprocess.Popen([sys.executable, "-m", "ivc.cli", "serve", f"replay:{path}", "--port", str(port),
                                "--pause", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        source = IgtlSource("127.0.0.1", port, retries=int(DEADLINE_S / 0.25))
        source.open()  # retried until the command listens
        recorders = record(source, 24)  # a tenth of a second of the first step, in real time
        assert set(recorders) == {"wand_sweep"}
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=DEADLINE_S)
        source.close()
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, err
    assert "served" in out and "Traceback" not in err


def test_a_missing_source_module_is_a_clear_error():
    if importlib.util.find_spec("ivc.collect.polhemus_serial") is not None:
        pytest.skip("the polhemus: source is installed")
    with pytest.raises(LiveError, match="polhemus:/dev/ttyUSB0.*not available"):
        serve_source("polhemus:/dev/ttyUSB0")
