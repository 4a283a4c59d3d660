"""The simulated AC tracker (:class:`SimulatedTracker`): true sensor poses in, what a tracker reports out.

For each sample it forms ``S = Tᵀ (f_D(r) + G(r))`` (zero G in free space), applies
the scene's noise model (gain drift, white noise, dropouts, saturation close to the
source) and, like a commercial unit, also reports the pose of its own solver, which is
distorted wherever G is not zero: the closed-form dipole solver (docs/math.md §3) by default,
or the least-squares one (``ivc.pose.tracker_solver``).

With an imperfect ``tracker`` (:class:`ivc.dipole.tracker.Tracker`: coil gains,
cross-talk, coil offsets) the free-space part is the tracker's own model and the
secondary field is driven by its source moments, ``Bᵀ Tᵀ G A``; the reported pose is
then its solver's on the raw signal (a solver that assumes an ideal device). The
ideal tracker (the default) takes exactly the code path it always took.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import dipole, rotations
from ivc.dipole.tracker import Tracker
from ivc.pose.tracker_solver import reported_pose
from ivc.session import Step
from ivc.sim.field import SecondaryField
from ivc.sim.scene import NoiseSpec


def noise_sigma(noise: NoiseSpec) -> float:
    """Absolute white-noise level per signal entry: ``signal_relative`` × rms entry of f_D at the reference range."""
    return noise.signal_relative * np.sqrt(6.0 / 9.0) / noise.reference_range**3


def measure(
    positions: np.ndarray,
    quaternions: np.ndarray,
    *,
    secondary: SecondaryField | None,
    noise: NoiseSpec,
    rate_hz: float,
    hemisphere: str,
    rng: np.random.Generator,
    description: str = "",
    sensor_prefix: str = "sensor",
    solver: str = "closed-form",
    tracker: Tracker | None = None,
) -> Step:
    """Simulate a tracker recording of true sensor poses ``positions`` (F, N, 3), ``quaternions`` (F, N, 4)."""
    frames, sensors = positions.shape[:2]
    T = rotations.to_matrix(quaternions)
    G = secondary(positions) if secondary is not None else None
    if tracker is None or tracker.is_ideal:
        S = dipole.signal(positions, T, G)
    else:
        S = tracker.signal(positions, T)
        if G is not None:
            S += tracker.sensor_moments.T @ np.swapaxes(T, -1, -2) @ G @ tracker.source_moments
    if noise.drift_relative_per_sqrt_s > 0:
        steps = noise.drift_relative_per_sqrt_s / np.sqrt(rate_hz) * rng.standard_normal((frames, 3))
        S *= 1.0 + np.cumsum(steps, axis=0)[:, None, None, :]  # slow gain drift of each source coil
    sigma = noise_sigma(noise)
    if sigma > 0:
        S += sigma * rng.standard_normal(S.shape)
    saturated = np.linalg.norm(positions, axis=-1) < noise.saturation_range
    dropped = rng.random((frames, sensors)) < noise.dropout_rate
    valid = ~(saturated | dropped)
    S[~valid] = np.nan
    position, T_reported = reported_pose(S, solver, hemisphere)
    with np.errstate(invalid="ignore"):
        quaternion = rotations.from_matrix(T_reported)
    quaternion[~valid] = np.nan
    return Step(
        time=np.arange(frames) / rate_hz,
        signal=S,
        position=position,
        quaternion=quaternion,
        valid=valid,
        sample_rate_hz=rate_hz,
        sensor_ids=[f"{sensor_prefix}{i}" for i in range(sensors)],
        description=description,
    )


@dataclass(frozen=True)
class SimulatedTracker:
    """The simulated device: a tracker with ``noise`` sampling at ``rate_hz`` (Hz) in ``hemisphere``, reporting the
    poses of its pose ``solver`` (``closed-form`` or ``least-squares``); ``model``: an imperfect device's own coil
    model (:class:`ivc.dipole.tracker.Tracker`; None: ideal dipoles). :meth:`measure` is :func:`measure` with these.
    """

    noise: NoiseSpec
    rate_hz: float
    hemisphere: str = "+x"
    solver: str = "closed-form"
    model: Tracker | None = None

    def measure(self, positions: np.ndarray, quaternions: np.ndarray, *, secondary: SecondaryField | None,
                rng: np.random.Generator, description: str = "", sensor_prefix: str = "sensor") -> Step:
        """A recording of true sensor poses ``positions`` (F, N, 3) m, ``quaternions`` (F, N, 4), in the
        secondary field ``secondary`` (None: free space)."""
        return measure(positions, quaternions, secondary=secondary, noise=self.noise, rate_hz=self.rate_hz,
                       hemisphere=self.hemisphere, rng=rng, description=description, sensor_prefix=sensor_prefix,
                       solver=self.solver, tracker=self.model)
