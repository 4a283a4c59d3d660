"""Live correction over OpenIGTLink (issue: export/report/live): 16 sensors at 240 Hz on loopback.

A paced source (a raw TCP server in this process) sends one NDARRAY signal matrix per sensor
per frame (what a Liberty-class tracker measures), stamped with its frame number;
``ivc correct --live`` runs as its own process, as it would in use; a consumer in this process
receives the corrected TRANSFORMs and notes when each arrives.
Latency = arrival of the corrected pose at the consumer − the source's send of the raw pose, so
it includes two loopback hops. Baseline, same run and same threads: the source sending straight
to the consumer (the hops alone). A frame is dropped if any of its 16 corrected poses never
arrives. Duration: IVC_LIVE_SECONDS (default 60).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import Figure
from ivc import dipole, rotations
from ivc.igtl import Framer, NDArrayMessage
from ivc.lut import Grid, LookupTable
from ivc.lut import write as write_lut

SENSORS, RATE_HZ = 16, 240.0
BASE = 1_000_000.0  # timestamps: BASE + frame / RATE_HZ


def _table() -> LookupTable:
    """A smooth secondary field of a few millimetres of pose distortion around (0.5, 0, 0) m."""
    from tests.test_lut import CENTRE, quadratic_field

    grid = Grid(CENTRE - 0.25, 0.025, (21, 21, 21))
    values = 0.2 * quadratic_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3)
    return LookupTable(grid, values, np.ones(grid.shape, bool), np.full(grid.shape, 100))


def _signals(table: LookupTable, frames: int, rng) -> np.ndarray:
    """Signal matrices (frames, SENSORS, 3, 3) of sensors wandering in the mapped ball, turning up to 0.8 rad."""
    from tests.test_lut import CENTRE

    t = np.arange(frames)[:, None] / RATE_HZ
    phase = rng.uniform(0, 2 * np.pi, (SENSORS, 3))
    r = CENTRE + 0.12 * np.sin(2 * np.pi * 0.3 * t[..., None] + phase)
    q = rotations.from_rotvec(0.8 * np.sin(2 * np.pi * 0.2 * t[..., None] + phase))
    T = rotations.to_matrix(q)
    return dipole.signal(r, T, table.field()(r))


def _source(sock: socket.socket, signals: np.ndarray, sent: np.ndarray) -> None:
    """Send frame k at k / RATE_HZ after the start; sent[k] = perf_counter at its send."""
    start = time.perf_counter() + 0.2
    for k in range(len(signals)):
        frame = b"".join(NDArrayMessage(signals[k, n], timestamp=BASE + k / RATE_HZ, device_name=f"S{n}").pack()
                         for n in range(SENSORS))
        while (wait := start + k / RATE_HZ - time.perf_counter()) > 0:
            time.sleep(min(wait, 0.001) if wait > 0.0015 else 0)
        sent[k] = time.perf_counter()
        sock.sendall(frame)


def consume(sock: socket.socket, arrived: np.ndarray, names: dict[str, int], stop: threading.Event,
            rate_hz: float, bufsize: int = 1 << 16) -> None:
    """arrived[k, n] = perf_counter when device ``names``' sensor n's message of frame k arrived
    (frame k stamped BASE + k / rate_hz); other messages are read and ignored."""
    framer = Framer()
    sock.settimeout(0.2)
    while not stop.is_set():
        try:
            data = sock.recv(bufsize)
        except TimeoutError:
            continue
        if not data:
            return
        now = time.perf_counter()
        framer.feed(data)
        for f in framer.messages():
            n = names.get(f.device_name)
            if n is not None:
                k = int(round((f.timestamp - BASE) * rate_hz))
                if 0 <= k < len(arrived):
                    arrived[k, n] = now


def _stream(signals, connect_consumer, suffix) -> tuple[np.ndarray, np.ndarray]:
    """Run source and consumer; (latency (frames, SENSORS) s, NaN where never arrived)."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    consumer = connect_consumer(port)
    upstream, _ = listener.accept()
    upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sent = np.full(len(signals), np.nan)
    arrived = np.full((len(signals), SENSORS), np.nan)
    stop = threading.Event()
    names = {f"S{n}{suffix}": n for n in range(SENSORS)}
    reader = threading.Thread(target=consume, args=(consumer, arrived, names, stop, RATE_HZ))
    reader.start()
    _source(upstream, signals, sent)
    time.sleep(0.5)
    stop.set()
    reader.join()
    for s in (upstream, consumer, listener):
        s.close()
    return arrived - sent[:, None], sent


def run() -> list[Figure]:
    seconds = float(os.environ.get("IVC_LIVE_SECONDS", 60))
    frames = int(seconds * RATE_HZ)
    table = _table()
    signals = _signals(table, frames, np.random.default_rng(7))

    def direct(port):
        s = socket.create_connection(("127.0.0.1", port))
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return s

    baseline, _ = _stream(signals[: int(5 * RATE_HZ)], direct, "")

    with tempfile.TemporaryDirectory() as tmp:
        lut_path = Path(tmp) / "map.h5"
        write_lut(table, lut_path)
        publish = socket.socket()
        publish.bind(("127.0.0.1", 0))
        publish_port = publish.getsockname()[1]
        publish.close()
        procs = {}

        def through_ivc(port):
            procs["ivc"] = subprocess.Popen(
                [sys.executable, "-m", "ivc.cli", "correct", str(lut_path), "--live", f"igtl://127.0.0.1:{port}",
                 "--publish", f"127.0.0.1:{publish_port}"], stderr=subprocess.PIPE, text=True)
            deadline = time.monotonic() + 60
            while True:
                try:
                    s = socket.create_connection(("127.0.0.1", publish_port), timeout=0.2)
                    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    return s
                except OSError:
                    if time.monotonic() > deadline or procs["ivc"].poll() is not None:
                        raise RuntimeError("ivc correct --live did not start") from None
                    time.sleep(0.05)

        latency, _ = _stream(signals, through_ivc, "_ivc")
        procs["ivc"].send_signal(signal.SIGINT)
        try:
            _, err = procs["ivc"].communicate(timeout=30)
        except subprocess.TimeoutExpired:
            procs["ivc"].kill()
            _, err = procs["ivc"].communicate()
            err += "\n(ivc did not stop within 30 s of SIGINT: killed)"
    dropped = int(np.sum(np.any(np.isnan(latency), axis=1)))
    ours = float(np.nanmedian(latency)) * 1e3
    hops = float(np.nanmedian(baseline)) * 1e3
    p99 = float(np.nanpercentile(latency, 99)) * 1e3
    print(f"  ivc: {err.strip().splitlines()[-1] if err.strip() else '(no summary)'}", file=sys.stderr)
    return [
        Figure(f"live 16 sensors @240 Hz, median latency ({seconds:.0f} s)", ours, "ms", "loopback hops alone", hops,
               "<= 2 ms", ours <= 2.0, higher_is_better=False),
        Figure("live 16 sensors @240 Hz, 99th percentile latency", p99, "ms", "loopback hops alone", hops, "",
               None, higher_is_better=False),
        Figure(f"live dropped frames of {frames}", dropped, "frames", "", float("nan"), "0", dropped == 0,
               higher_is_better=False),
    ]
