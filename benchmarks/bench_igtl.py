"""The igtl:// source at a full Liberty's load (issue 36): 16 sensors at 240 Hz through an ``ivc serve`` server.

1. Throughput: 10 minutes of tracker time (144,000 frames, 2.3 million TRANSFORMs with PLUS's status metadata)
   served as fast as the client takes them (the server waits for it: ``lossless``) and read by
   :class:`~ivc.collect.igtl.IgtlSource` in this process: every frame must arrive, faster than real time.
   Baseline, same run: pyigtl's own decoding (its client's ``parse_header`` and ``unpack``) of the same messages,
   frames per second of one core.
2. CPU at real rate: IGTL_REALTIME_SECONDS (default 20) s of the same stream paced at 240 Hz; the collector's
   thread CPU time (``time.thread_time``) over that span, as a share of one core: at most 20 %. Baseline, same run
   and same stream: a second client that only receives the bytes (raw socket reads), its thread CPU the same way.
Durations: IGTL_TRACKER_MINUTES (default 10).
"""

from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np

from benchmarks.harness import Figure
from ivc import rotations
from ivc.app.serve import IgtlServer
from ivc.collect.igtl import IgtlSource
from ivc.collect.stream import Sample, SessionSource
from ivc.session import Session, Step

SENSORS, RATE_HZ = 16, 240.0


def _session(frames: int, rng) -> Session:
    """16 sensors wandering smoothly (metres, source frame), one step of ``frames`` frames."""
    t = np.arange(frames)[:, None, None] / RATE_HZ
    phase = rng.uniform(0, 2 * np.pi, (1, SENSORS, 3))
    position = 0.4 + 0.2 * np.sin(2 * np.pi * 0.3 * t + phase) + rng.normal(0, 1e-5, (frames, SENSORS, 3))
    quaternion = rotations.from_rotvec(0.8 * np.sin(2 * np.pi * 0.2 * t + phase))
    step = Step(time=np.arange(frames) / RATE_HZ, position=position, quaternion=quaternion,
                sensor_ids=[f"Sensor{i}" for i in range(SENSORS)])
    return Session(steps={"wand_sweep": step})


def _names() -> list[str]:
    return [f"Sensor{i}ToTracker" for i in range(SENSORS)]


def _throughput(frames: int, rng) -> tuple[int, float, float]:
    """(frames received, wall seconds, collector CPU seconds) of ``frames`` frames served losslessly."""
    source = SessionSource(_session(frames, rng), chunk=512)
    server = IgtlServer(source, 0, lossless=True, start_on_connect=True, signals=False)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    received = 0
    with IgtlSource(*server.address, sensors=_names(), retries=1, stale_after_s=3600) as client:
        start, cpu = time.perf_counter(), time.thread_time()
        try:
            while received < frames:
                received += sum(isinstance(i, Sample) and bool(i.valid.all()) for i in client.read(1.0))
        except Exception:  # noqa: BLE001 - the server ended: frames are counted
            pass
        wall, cpu = time.perf_counter() - start, time.thread_time() - cpu
    thread.join(60)
    return received, wall, cpu


def _pyigtl_rate(frames: int, rng) -> float:
    """Frames per CPU second of pyigtl decoding the same messages (header parse, message object, unpack)."""
    from pyigtl.messages import MessageBase

    source = SessionSource(_session(frames, rng), chunk=frames)
    server = IgtlServer(source, 0, signals=False)
    source.open()
    data = b"".join(m for s in source.read(0.0) for m in server.encode(s, tuple(n[:-9] for n in _names())))
    server.close()
    start = time.thread_time()
    at = 0
    while at < len(data):
        header = MessageBase.parse_header(data[at:at + 58])
        message = MessageBase.create_message(header["message_type"])
        end = at + 58 + header["body_size"]
        message.unpack(header, data[at + 58:end])
        at = end
    return frames / (time.thread_time() - start)


def _realtime(seconds: float, rng) -> tuple[float, float, int]:
    """(collector CPU share, raw reader CPU share, frames received) over ``seconds`` of a 240 Hz stream."""
    frames = int(seconds * RATE_HZ) + int(2 * RATE_HZ)
    source = SessionSource(_session(frames, rng), realtime=True)
    server = IgtlServer(source, 0, signals=False)
    result = {}

    def raw():
        with socket.create_connection(server.address) as sock:
            sock.settimeout(5.0)
            start, cpu = time.perf_counter(), time.thread_time()
            while time.perf_counter() - start < seconds + 1.0:
                try:
                    if not sock.recv(1 << 20):
                        break
                except TimeoutError:
                    break
            result["raw"] = (time.thread_time() - cpu) / (time.perf_counter() - start)

    reader = threading.Thread(target=raw, daemon=True)
    stop = threading.Event()
    thread = threading.Thread(target=server.run, kwargs={"stop": stop}, daemon=True)
    thread.start()
    received = 0
    with IgtlSource(*server.address, sensors=_names(), retries=1, stale_after_s=3600) as client:
        reader.start()
        while received < RATE_HZ:  # one second to settle
            received += sum(isinstance(i, Sample) for i in client.read(0.5))
        start, cpu, received = time.perf_counter(), time.thread_time(), 0
        while time.perf_counter() - start < seconds:
            received += sum(isinstance(i, Sample) for i in client.read(0.5))
        share = (time.thread_time() - cpu) / (time.perf_counter() - start)
    reader.join(seconds + 30)
    stop.set()
    thread.join(30)
    return share, result.get("raw", float("nan")), received


def run() -> list[Figure]:
    rng = np.random.default_rng(36)
    minutes = float(os.environ.get("IGTL_TRACKER_MINUTES", "10"))
    seconds = float(os.environ.get("IGTL_REALTIME_SECONDS", "20"))
    frames = int(minutes * 60 * RATE_HZ)
    received, wall, cpu = _throughput(frames, rng)
    pyigtl = _pyigtl_rate(int(10 * RATE_HZ), rng)
    share, raw, realtime_frames = _realtime(seconds, rng)
    return [
        Figure(f"igtl {minutes:g} min x16 @240Hz: frames received", received, "frames", "frames served", frames,
               target="all (none lost)", passed=received == frames),
        Figure("igtl source, faster than real time", frames / RATE_HZ / wall, "x realtime", "pyigtl decode (x rt)",
               pyigtl / RATE_HZ, target="> 1", passed=frames / RATE_HZ / wall > 1.0),
        Figure("igtl source CPU per frame (throughput run)", cpu / max(received, 1) * 1e6, "us/frame",
               "pyigtl decode", 1e6 / pyigtl, target="-", higher_is_better=False),
        Figure(f"igtl collector CPU at 240 Hz x16 ({seconds:g} s)", 100 * share, "% of a core", "raw socket reads",
               100 * raw, target="<= 20 %", passed=share <= 0.20, higher_is_better=False),
        Figure("igtl frames received at real rate", realtime_frames / seconds, "frames/s", "tracker rate", RATE_HZ,
               target=">= 99 % of rate", passed=realtime_frames / seconds >= 0.99 * RATE_HZ),
    ]
