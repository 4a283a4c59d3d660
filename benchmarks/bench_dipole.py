"""Dipole signal matrices and closed-form pose (issue: foundation).

Targets: signal matrices >= 5x magpylib's dipole kernel (three unit moments) on 10^6
poses; closed-form pose >= 500,000 sensor-frames per second.
"""

from __future__ import annotations

import magpylib
import numpy as np

from benchmarks.harness import Figure, best_time
from ivc import dipole
from ivc import rotations as R

N = 1_000_000


def _poses(rng):
    d = rng.standard_normal((N, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 0] = np.abs(d[:, 0])
    r = d * rng.uniform(0.05, 2.0, (N, 1))
    return r, R.to_matrix(R.random(N, rng))


def _magpylib_field(r):
    moments = [np.tile(m, (len(r), 1)) for m in np.eye(3)]
    return [magpylib.core.dipole_Hfield(r, m) for m in moments]


def _python_loop(r, T):
    out = np.empty((len(r), 3, 3))
    for n in range(len(r)):
        rho = np.linalg.norm(r[n])
        f = (3.0 * np.outer(r[n], r[n]) / rho**2 - np.eye(3)) / rho**3
        out[n] = T[n].T @ f
    return out


def _lapack_pose(S):
    """The same closed form with NumPy's batched LAPACK (eigh + SVD): the plain-NumPy baseline."""
    B = np.swapaxes(S, -1, -2) @ S
    _, vectors = np.linalg.eigh(B)
    v = vectors[..., :, -1]
    v *= np.where(v[..., :1] < 0, -1.0, 1.0)
    r = (6.0 / np.trace(B, axis1=-2, axis2=-1))[..., None] ** (1 / 6) * v
    return r, R.nearest_rotation(dipole.field(r) @ np.swapaxes(S, -1, -2))


def run() -> list[Figure]:
    rng = np.random.default_rng(0)
    r, T = _poses(rng)
    t_ivc = best_time(lambda: dipole.signal(r, T))
    t_magpy = best_time(lambda: _magpylib_field(r), repeat=3)
    n_loop = 20_000
    t_loop = best_time(lambda: _python_loop(r[:n_loop], T[:n_loop]), repeat=1) * N / n_loop
    rate = N / t_ivc / 1e6
    figures = [
        Figure("dipole.signal, 1e6 (r, T)", rate, "M/s", "magpylib 3 moments", N / t_magpy / 1e6, ">= 5x magpylib",
               passed=t_magpy / t_ivc >= 5.0),
        Figure("dipole.signal vs per-point Python loop", rate, "M/s", "python loop", N / t_loop / 1e6, "(reference)"),
    ]
    S = dipole.signal(r, T)
    t_pose = best_time(lambda: dipole.closed_form_pose(S, "+x"), repeat=3)
    t_lapack = best_time(lambda: _lapack_pose(S), repeat=1)
    pose_rate = N / t_pose
    figures.append(
        Figure("closed_form_pose, 1e6 frames", pose_rate / 1e3, "k frames/s", "numpy eigh+svd", N / t_lapack / 1e3,
               ">= 500 k frames/s", passed=pose_rate >= 500_000)
    )
    r_est, T_est = dipole.closed_form_pose(S, "+x")
    figures.append(
        Figure("closed_form_pose max position error", np.abs(r_est - r).max() * 1e3, "mm", target="< 1e-6 mm",
               passed=np.abs(r_est - r).max() < 1e-9, higher_is_better=False)
    )
    return figures
