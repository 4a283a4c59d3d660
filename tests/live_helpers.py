"""Small live sources for the tests of guided collection: poses from arrays, and a source's labels removed."""

from __future__ import annotations

import dataclasses

import numpy as np

from ivc import rotations
from ivc.collect.stream import Sample


class ArraySource:
    """A live source without step labels (a real tracker's kind): poses (F, N, 3), (F, N, 4), ``chunk`` frames a
    read at 240 Hz; ``interrupt_at`` raises KeyboardInterrupt on that read (Ctrl-C arriving mid-read)."""

    def __init__(self, position, quaternion, valid=None, chunk=50, interrupt_at=None, names=None):
        self.position, self.quaternion = np.asarray(position, float), np.asarray(quaternion, float)
        self.valid = np.ones(self.position.shape[:2], bool) if valid is None else valid
        self.chunk, self.interrupt_at = chunk, interrupt_at
        self.sensor_names = tuple(names or (str(k) for k in range(self.position.shape[1])))
        self.sample_rate_hz = 240.0
        self.at = self.reads = 0

    def read(self, timeout_s):
        self.reads += 1
        if self.interrupt_at is not None and self.reads == self.interrupt_at:
            raise KeyboardInterrupt
        stop = min(self.at + self.chunk, len(self.position))
        out = [Sample(time=f / 240.0, valid=self.valid[f], position=self.position[f], quaternion=self.quaternion[f],
                      host_time=0.0) for f in range(self.at, stop)]
        self.at = stop
        return out

    @property
    def finished(self):
        return self.at >= len(self.position)


class Unlabelled:
    """A source's samples with their step labels removed: what a real tracker streams."""

    def __init__(self, source):
        self.source = source
        self.sensor_names, self.sample_rate_hz = source.sensor_names, source.sample_rate_hz

    def read(self, timeout_s):
        return [dataclasses.replace(s, step=None) if isinstance(s, Sample) else s for s in self.source.read(timeout_s)]

    @property
    def finished(self):
        return self.source.finished


def static_cube(frames, rng, noise=2e-5, moves=()):
    """8 cube sensors at rest with ``noise`` m of jitter; ``moves``: (frame, offset (3,) m) from which on the cube
    sits shifted."""
    base = 0.5 + 0.05 * rng.random((8, 3))
    q = rotations.random(8, rng)
    position = np.repeat(base[None], frames, axis=0) + noise * rng.standard_normal((frames, 8, 3))
    for frame, offset in moves:
        position[frame:] += offset
    turn = rotations.from_rotvec(noise * rng.standard_normal((frames, 8, 3)))
    return position, rotations.multiply(turn, np.broadcast_to(q, (frames, 8, 4)))
