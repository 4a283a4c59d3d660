"""Polhemus serial source (``polhemus:DEVICE``): a full Liberty, 16 stations at 240 Hz, through the pty emulator.

The emulated tracker (tests/polhemus_emulator.py) runs in a forked child process, so the CPU time measured is the
reading process's own. Both runs use ``PolhemusSource`` as ``ivc collect`` does (it configures the tracker: binary,
centimetres, hemisphere, output list 2,7,9, continuous).

1. Throughput: IVC_POLHEMUS_MINUTES (default 10) minutes of tracker time (144,000 frames of 16 records, 92 MB)
   streamed as fast as the reader takes them. Figures: tracker seconds per wall second (target > 1: faster than
   real time) and frames lost (target 0: the frame counts delivered are exactly the frames the tracker sent).
   Baseline, same run: the same byte stream copied raw through the pty (read and discarded, no parsing).
2. CPU at the real rate: IVC_POLHEMUS_SECONDS (default 20) s of frames paced at 240 Hz, each frame kept in a
   ``StepRecorder`` as a collected step would be. Figure: process CPU time / wall time of the reading process
   (target <= 20 % of one core), over those seconds rather than ten minutes. Baseline: the raw copy at the same rate.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import select
import time

import numpy as np

from benchmarks.harness import Figure

SENSORS, RATE_HZ = 16, 240.0
RECORD_BYTES = 40
CONFIGURE = b"P\rF1\rU1\rH*,1,0,0\rO*,2,7,9\rC\r"


def _tracker(connection, frames: int, rate_hz: float | None) -> None:
    """Child process: the emulated Liberty; sends its pty path, streams ``frames`` frames, waits to be stopped."""
    from tests.polhemus_emulator import PolhemusEmulator, smooth_poses

    positions, quaternions = smooth_poses(int(60 * RATE_HZ), SENSORS, seed=11)
    emulator = PolhemusEmulator(positions, quaternions, loop=True, max_frames=frames, rate_hz=rate_hz, chunk=120)
    emulator.start()
    connection.send(emulator.path)
    connection.recv()  # stop
    emulator.stop()


def _start(frames: int, rate_hz: float | None):
    parent, child = mp.get_context("fork").Pipe()
    process = mp.get_context("fork").Process(target=_tracker, args=(child, frames, rate_hz), daemon=True)
    process.start()
    if not parent.poll(60):
        raise RuntimeError("the emulated tracker did not start")
    return process, parent, parent.recv()


def _stop(process, connection) -> None:
    connection.send("stop")
    process.join(30)
    if process.is_alive():
        process.kill()


def _raw_copy(frames: int, rate_hz: float | None) -> tuple[float, float]:
    """(wall s, CPU s) to copy the byte stream of ``frames`` frames through the pty without parsing."""
    import serial

    process, connection, path = _start(frames, rate_hz)
    port = serial.Serial(path, 115200, timeout=0)
    port.write(CONFIGURE)
    wanted = frames * SENSORS * RECORD_BYTES
    got = 0
    deadline = time.monotonic() + 3600
    while not got:  # the first bytes start the clock
        if select.select([port.fileno()], [], [], 1.0)[0]:
            got += len(port.read(port.in_waiting or 1))
    wall, cpu = time.perf_counter(), time.process_time()
    while got < wanted and time.monotonic() < deadline:
        if select.select([port.fileno()], [], [], 1.0)[0]:
            got += len(port.read(port.in_waiting or 1))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    port.close()
    _stop(process, connection)
    return wall, cpu


def _through_ivc(frames: int, rate_hz: float | None, record: bool) -> tuple[float, float, np.ndarray, dict]:
    """(wall s, CPU s, delivered frame counts, source counts) reading ``frames`` frames with PolhemusSource."""
    from ivc.collect.polhemus_serial import PolhemusSource
    from ivc.collect.stream import Sample, StepRecorder

    process, connection, path = _start(frames, rate_hz)
    delivered = np.zeros(frames, np.int64)
    n = 0
    recorder = StepRecorder(SENSORS) if record else None
    deadline = time.monotonic() + 3600
    with PolhemusSource(path, stall_s=5.0) as source:
        wall, cpu = time.perf_counter(), time.process_time()
        while n < frames and time.monotonic() < deadline:
            for item in source.read(0.5):
                if isinstance(item, Sample):
                    if n < frames:
                        delivered[n] = item.frame
                    n += 1
                    if recorder is not None:
                        recorder.add(item)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        counts = dict(source.counts)
    _stop(process, connection)
    return wall, cpu, delivered[:n], counts


def run() -> list[Figure]:
    minutes = float(os.environ.get("IVC_POLHEMUS_MINUTES", 10))
    seconds = float(os.environ.get("IVC_POLHEMUS_SECONDS", 20))
    frames = int(minutes * 60 * RATE_HZ)
    tracker_s = frames / RATE_HZ

    raw_wall, _ = _raw_copy(frames, None)
    wall, _, delivered, counts = _through_ivc(frames, None, record=False)
    expected = 1000 + np.arange(frames)  # the emulator's frame counts
    lost = frames - int(np.count_nonzero(np.isin(expected, delivered)))
    in_order = delivered.size == frames and bool(np.all(np.diff(delivered) == 1))
    speed, raw_speed = tracker_s / wall, tracker_s / raw_wall

    paced = int(seconds * RATE_HZ)
    raw_rate_wall, raw_rate_cpu = _raw_copy(paced, RATE_HZ)
    rate_wall, rate_cpu, rate_delivered, _ = _through_ivc(paced, RATE_HZ, record=True)
    share, raw_share = 100 * rate_cpu / rate_wall, 100 * raw_rate_cpu / raw_rate_wall
    rate_lost = paced - rate_delivered.size
    print(f"  polhemus: {frames} frames in {wall:.1f} s ({counts}); real rate: {rate_delivered.size} of {paced} frames "
          f"in {rate_wall:.1f} s, {rate_cpu:.2f} s CPU", flush=True)
    return [
        Figure(f"polhemus 16x240 Hz, {minutes:g} min streamed: speed", speed, "x realtime", "raw pty copy", raw_speed,
               "> 1x (faster than real)", speed > 1.0 and in_order),
        Figure(f"polhemus 16x240 Hz frames lost of {frames}", lost, "frames", "", float("nan"), "0",
               lost == 0 and in_order, higher_is_better=False),
        Figure(f"polhemus 16x240 Hz real rate CPU ({seconds:g} s)", share, "% of core", "raw pty copy", raw_share,
               "<= 20 %", share <= 20.0 and rate_lost == 0, higher_is_better=False),
    ]
