"""Closed-form dipole pose (Himberg 2010, eq. 74-77; docs/math.md §3).

This is what a commercial tracker computes, and in a distorted room it is the
*uncompensated* ("dipole") solution of Himberg 2010's Table 24.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc.dipole import kernels as _kernels
from ivc.dipole.field import flat_batch
from ivc.errors import InputError

FloatArray = NDArray[np.float64]

HEMISPHERES = ("+x", "-x", "+y", "-y", "+z", "-z")


def hemisphere_vector(hemisphere: str) -> FloatArray:
    """Unit vector of a declared hemisphere such as ``"+x"`` (the side the sensors are on)."""
    if hemisphere not in HEMISPHERES:
        raise InputError(f"hemisphere must be one of {', '.join(HEMISPHERES)}; got {hemisphere!r}")
    axis = "xyz".index(hemisphere[1])
    v = np.zeros(3)
    v[axis] = 1.0 if hemisphere[0] == "+" else -1.0
    return v


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
    _kernels.closed_form_pose_kernel(flat, h, r, T)
    return r.reshape(lead + (3,)), T.reshape(lead + (3, 3))
