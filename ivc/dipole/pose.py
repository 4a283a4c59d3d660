"""Closed-form dipole pose (Himberg 2010, eq. 74-77; docs/math.md §3).

This is what a commercial tracker computes, and in a distorted room it is the
*uncompensated* ("dipole") solution of Himberg 2010's Table 24.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc import compiled
from ivc.dipole import kernels as _kernels
from ivc.dipole import numpy_kernels
from ivc.dipole.field import flat_batch
from ivc.errors import InputError

FloatArray = NDArray[np.float64]

HEMISPHERES = ("+x", "-x", "+y", "-y", "+z", "-z")
#: the source distances (m) a usable signal matrix may stand for: in free space ``‖S‖_F = √6 / |r|³``
#: (docs/math.md §3), so this bounds ‖S‖_F to about 2.4e-12 … 2.4e12 (signal units), far beyond any tracker's
#: reach either way, and keeps every square and product of a solve inside double precision
USABLE_RANGE_M = (1e-4, 1e4)
_NORM_BOUNDS = (np.sqrt(6.0) / USABLE_RANGE_M[1] ** 3, np.sqrt(6.0) / USABLE_RANGE_M[0] ** 3)


def hemisphere_vector(hemisphere: str) -> FloatArray:
    """Unit vector of a declared hemisphere such as ``"+x"`` (the side the sensors are on)."""
    if hemisphere not in HEMISPHERES:
        raise InputError(f"hemisphere must be one of {', '.join(HEMISPHERES)}; got {hemisphere!r}")
    axis = "xyz".index(hemisphere[1])
    v = np.zeros(3)
    v[axis] = 1.0 if hemisphere[0] == "+" else -1.0
    return v


def usable_signals(S: ArrayLike) -> NDArray[np.bool_]:
    """Whether each signal matrix of ``S`` (..., 3, 3) can be solved at all: every entry finite and the
    Frobenius norm that of a source between :data:`USABLE_RANGE_M` metres away (all zeros, denormals such
    as 1e-300 and huge values such as 1e300 are not). The wrappers of the compiled solves mark the others
    invalid input before the kernels see them. Shape (...)."""
    S = np.asarray(S, dtype=np.float64)
    if S.shape[S.ndim - 2:] != (3, 3) or S.ndim < 2:
        raise InputError(f"S must have shape (..., 3, 3), got {S.shape}")
    flat = S.reshape(S.shape[:-2] + (9,))
    finite = np.all(np.isfinite(flat), axis=-1)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        norm = np.sqrt(np.sum(np.where(finite[..., None], flat, 0.0) ** 2, axis=-1))
    return finite & (norm >= _NORM_BOUNDS[0]) & (norm <= _NORM_BOUNDS[1])


def closed_form_pose(S: ArrayLike, hemisphere: str = "+x") -> tuple[FloatArray, FloatArray]:
    """Pose of each signal matrix by the closed-form dipole inversion.

    Steps (docs/math.md §3): ``B = SᵀS`` is rotation invariant; the range is
    ``R = (6 / tr B)^(1/6)`` (eq. 75); the direction is the principal eigenvector of
    ``B`` (eq. 76 is one power-iteration step of it) with its sign chosen so that the
    position lies in the declared hemisphere; the orientation is the rotation
    nearest to eq. 77 in the least-squares sense, the orthogonal Procrustes solution
    of ``min_T ‖S − Tᵀ f_D(r)‖_F``, which equals ``f_D(r) S⁻¹`` in free space.

    Parameters
    ----------
    S : array, shape (..., 3, 3)
        Signal matrices (row = sensor coil, column = source coil).
    hemisphere : str
        ``"+x"``, ``"-x"``, ``"+y"``, ``"-y"``, ``"+z"`` or ``"-z"``.

    Returns
    -------
    position : array, shape (..., 3)
        Metres, source frame.
    rotation : array, shape (..., 3, 3)
        Sensor orientation ``T`` (columns are sensor axes in the source frame).

    Notes
    -----
    The dipole model cannot tell ``r`` from ``−r`` (``f_D(−r) = f_D(r)``). A sensor
    that is really in the other hemisphere is returned at the mirrored position
    ``−r`` with its true orientation. Signal matrices that are not finite give NaN.
    """
    h = hemisphere_vector(hemisphere)
    flat, lead = flat_batch(S, (3, 3), "S")
    r = np.empty((flat.shape[0], 3))
    T = np.empty((flat.shape[0], 3, 3))
    compiled.choose(_kernels.closed_form_pose_kernel, len(flat), compiled.VECTORISED,
                    numpy_kernels.closed_form_pose_kernel)(flat, h, r, T)
    return r.reshape(lead + (3,)), T.reshape(lead + (3, 3))
