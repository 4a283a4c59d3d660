"""The simulator's tracker noise against a real tracker's (reference figures, no target).

The simulator's noise is absolute: one standard deviation per signal entry, ``signal_relative`` at
``reference_range`` (docs/simulator.md, "Noise"; 1e-4 at 0.5 m in every built-in scene). Its effect
on one frame's pose is the Cramér-Rao bound ``ivc.pose.precision.pose_precision`` (free space here).

The real tracker: the Polhemus Liberty recordings of ``shared/data/polhemus_liberty/`` (sensor 1 is
static in each; positions read as inches, the Liberty's default, which the files do not state). For
each, the static sensor's 3-D position RMS about its mean over the whole recording (an upper bound
of its white noise: it also holds drift) and its frame-to-frame jitter (the robust spread of
successive differences over sqrt(2), per axis, in quadrature; a lower bound where the tracker
filters its output), against the simulator's single-frame floor at the sensor's own mean pose and
range with the built-in scenes' noise. Orientation the same way. Skipped when the recordings are
not there (``shared/`` sits beside the repository).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.harness import Figure
from ivc import rotations
from ivc.collect import read_recording
from ivc.lut.signal_noise import robust_sigma
from ivc.pose.precision import pose_precision
from ivc.sim import load_scene
from ivc.sim.tracker import noise_sigma

LIBERTY = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "polhemus_liberty"
STATIC = 0  # sensor 1 of the files: static in every recording (shared/data/README.md)


def _jitter(values: np.ndarray) -> float:
    """Frame-to-frame white-noise estimate of (N, 3) samples: each axis's robust spread of successive differences
    (the estimator `ivc fit` measures the signal noise with), in quadrature."""
    return float(np.sqrt(np.sum(robust_sigma(np.diff(values, axis=0)) ** 2)))


def _static_noise(position: np.ndarray, quaternion: np.ndarray) -> dict:
    """RMS about the mean and frame-to-frame jitter of a static sensor's position (m) and orientation (rad)."""
    mean_q = rotations.mean(quaternion)
    turns = rotations.to_rotvec(rotations.multiply(quaternion, rotations.conjugate(mean_q)[None]))
    return {"position_rms": float(np.sqrt(np.mean(np.sum((position - position.mean(axis=0)) ** 2, axis=1)))),
            "position_jitter": _jitter(position),
            "orientation_rms": float(np.sqrt(np.mean(np.sum(turns**2, axis=1)))),
            "orientation_jitter": _jitter(turns),
            "mean_position": position.mean(axis=0), "mean_quaternion": mean_q}


def run() -> list[Figure]:
    if not LIBERTY.exists():
        print(f"skipped: {LIBERTY} is not there")
        return []
    sigma = noise_sigma(load_scene("default").noise)
    figures = []
    for path in sorted(LIBERTY.glob("*.csv")):
        step, _ = read_recording(path)
        ok = step.valid_mask[:, STATIC]
        real = _static_noise(step.position[ok, STATIC], step.quaternion[ok, STATIC])
        floor_m, floor_rad = pose_precision(real["mean_position"][None], real["mean_quaternion"][None], sigma)
        label = f"{path.stem[9:24]} static sensor at {1000 * np.linalg.norm(real['mean_position']):.0f} mm"
        for kind in ("rms", "jitter"):
            figures.append(Figure(f"{label}: position {kind}", 1000 * real[f"position_{kind}"], "mm",
                                  "simulator's floor there", 1000 * float(floor_m[0]), "(reference)",
                                  higher_is_better=False))
        figures.append(Figure(f"{label}: orientation rms", 1000 * real["orientation_rms"], "mrad",
                              "simulator's floor there", 1000 * float(floor_rad[0]), "(reference)",
                              higher_is_better=False))
    return figures
