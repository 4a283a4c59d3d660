"""Live correction while PLUS also streams video: 240 Hz TRANSFORMs of 3 tools interleaved with 30 fps
1280x1024 IMAGE messages (1.3 MB each) on one OpenIGTLink connection, through ``ivc correct --live``.

The paced source (in this process) sends, on one socket as PLUS does, each tracking frame at k / 240 s
(three TRANSFORMs in mm, the tools' reported poses) and an 8-bit 1280x1024 IMAGE every 1/30 s between
them; ``ivc correct --live`` runs as its own process; a consumer here receives the corrected TRANSFORMs.
Tracking latency = arrival of a corrected pose − the send of its raw pose: it includes two loopback
hops and the wait behind any image in the same TCP stream. Baseline, same run and same threads: the
same mixed stream from the source straight to the consumer (the hops and images alone). A tracking
frame is dropped if any of its corrected poses never arrives. Duration: IVC_LIVE_SECONDS (default 30).
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
import pyigtl

from benchmarks.bench_live import BASE, _table, consume
from benchmarks.harness import Figure
from ivc import dipole, rotations
from ivc.igtl import encode_transforms
from ivc.live.loop import output_device_name
from ivc.lut import write as write_lut

TOOLS, RATE_HZ, FPS = ("Probe", "Reference", "Stylus"), 240.0, 30.0
WIDTH, HEIGHT = 1280, 1024


def _matrices(table, frames: int, rng) -> np.ndarray:
    """Reported poses (frames, tools, 4, 4), mm, float32: the tools wander in the mapped ball."""
    from tests.helpers import CENTRE

    t = np.arange(frames)[:, None] / RATE_HZ
    phase = rng.uniform(0, 2 * np.pi, (len(TOOLS), 3))
    r = CENTRE + 0.12 * np.sin(2 * np.pi * 0.3 * t[..., None] + phase)
    T = rotations.to_matrix(rotations.from_rotvec(0.8 * np.sin(2 * np.pi * 0.2 * t[..., None] + phase)))
    S = dipole.signal(r, T, table.field()(r))
    position, rotation = dipole.closed_form_pose(S)
    m = np.zeros((frames, len(TOOLS), 4, 4))
    m[..., :3, :3], m[..., :3, 3], m[..., 3, 3] = rotation, position * 1000.0, 1.0
    return m.astype(np.float32)


def _image() -> bytes:
    pixels = np.random.default_rng(3).integers(0, 256, (1, HEIGHT, WIDTH), dtype=np.uint8)
    return pyigtl.ImageMessage(pixels, device_name="Video").pack()


def _source(sock, matrices, image, sent, fps=FPS) -> int:
    """Tracking frame k at k / RATE_HZ, an image whenever one is due before it; sent[k] = its send time.
    Returns the number of images sent."""
    names = [f"{tool}ToTracker" for tool in TOOLS]
    frames = [b"".join(encode_transforms(names, [BASE + k / RATE_HZ] * len(TOOLS), matrices[k].astype(float)))
              for k in range(len(matrices))]
    start = time.perf_counter() + 0.2
    images = 0
    for k, frame in enumerate(frames):
        due = start + k / RATE_HZ
        while fps and images / fps <= k / RATE_HZ:  # the next image is due before this frame
            while (wait := start + images / fps - time.perf_counter()) > 0:
                time.sleep(min(wait, 0.001) if wait > 0.0015 else 0)
            sock.sendall(image)
            images += 1
        while (wait := due - time.perf_counter()) > 0:
            time.sleep(min(wait, 0.001) if wait > 0.0015 else 0)
        sent[k] = time.perf_counter()
        sock.sendall(frame)
    return images


def _stream(matrices, image, connect_consumer, suffix, fps=FPS):
    listener = socket.create_server(("127.0.0.1", 0))
    consumer = connect_consumer(listener.getsockname()[1])
    upstream, _ = listener.accept()
    upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sent = np.full(len(matrices), np.nan)
    arrived = np.full((len(matrices), len(TOOLS)), np.nan)
    stop = threading.Event()
    names = {(output_device_name(f"{tool}ToTracker") if suffix else f"{tool}ToTracker"): n
             for n, tool in enumerate(TOOLS)}
    reader = threading.Thread(target=consume, args=(consumer, arrived, names, stop, RATE_HZ, 1 << 20))
    reader.start()
    images = _source(upstream, matrices, image, sent, fps)
    time.sleep(0.5)
    stop.set()
    reader.join()
    for s in (upstream, consumer, listener):
        s.close()
    return arrived - sent[:, None], images


def _connect(port, timeout=0.2):
    s = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def _through_ivc(lut_path, matrices, image, fps):
    """The stream through ``ivc correct --live`` in its own process: (latency, images sent, its stderr)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        publish_port = probe.getsockname()[1]
    procs = {}

    def connect(port):
        procs["ivc"] = subprocess.Popen(
            [sys.executable, "-m", "ivc.cli", "correct", str(lut_path), "--live", f"igtl://127.0.0.1:{port}",
             "--publish", f"127.0.0.1:{publish_port}"], stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while True:
            try:
                return _connect(publish_port)
            except OSError:
                if time.monotonic() > deadline or procs["ivc"].poll() is not None:
                    raise RuntimeError("ivc correct --live did not start") from None
                time.sleep(0.05)

    latency, images = _stream(matrices, image, connect, "_ivc", fps)
    procs["ivc"].send_signal(signal.SIGINT)
    try:
        _, err = procs["ivc"].communicate(timeout=30)
    except subprocess.TimeoutExpired:
        procs["ivc"].kill()
        _, err = procs["ivc"].communicate()
    return latency, images, err


def run() -> list[Figure]:
    seconds = float(os.environ.get("IVC_LIVE_SECONDS", 30))
    frames = int(seconds * RATE_HZ)
    table = _table()
    matrices = _matrices(table, frames, np.random.default_rng(11))
    image = _image()
    baseline, _ = _stream(matrices[: int(5 * RATE_HZ)], image, _connect, "")

    with tempfile.TemporaryDirectory() as tmp:
        lut_path = Path(tmp) / "map.h5"
        write_lut(table, lut_path)
        latency, images, err = _through_ivc(lut_path, matrices, image, FPS)
        # reference, same run: the tracking stream alone through ivc (what the images add)
        alone, _, _ = _through_ivc(lut_path, matrices[: int(10 * RATE_HZ)], image, 0.0)
    dropped = int(np.sum(np.any(np.isnan(latency), axis=1)))
    median, p99 = (float(np.nanpercentile(latency, q)) * 1e3 for q in (50, 99))
    hops, hops99 = (float(np.nanpercentile(baseline, q)) * 1e3 for q in (50, 99))
    print(f"  ivc: {err.strip().splitlines()[-1] if err.strip() else '(no summary)'}; {images} images sent",
          file=sys.stderr)
    label = f"{len(TOOLS)} tools @240 Hz + 30 fps {WIDTH}x{HEIGHT} IMAGE"
    return [
        Figure(f"{label}, median tracking latency ({seconds:.0f} s)", median, "ms", "same stream, hops alone",
               hops, "<= 2 ms", median <= 2.0, higher_is_better=False),
        Figure(f"{label}, p99 tracking latency", p99, "ms", "same stream, hops alone p99", hops99, "<= 10 ms",
               p99 <= 10.0, higher_is_better=False),
        Figure(f"{label}, dropped tracking frames of {frames}", dropped, "frames", "", float("nan"), "0",
               dropped == 0, higher_is_better=False),
        Figure("(reference) the tracking alone through ivc, median", float(np.nanmedian(alone)) * 1e3, "ms",
               "same stream, hops alone", hops, "", None, higher_is_better=False),
        Figure("(reference) the tracking alone through ivc, p99", float(np.nanpercentile(alone, 99)) * 1e3, "ms",
               "same stream, hops alone p99", hops99, "", None, higher_is_better=False),
    ]
