"""The AC dipole field model (Himberg 2010, eq. 71-73; docs/math.md §2).

All positions are in metres in the source frame. Signal matrices are normalised so
that in free space ``S = Tᵀ f_D(r)`` exactly (docs/math.md §1): row ``i`` is sensor
coil ``i``, column ``j`` is source coil ``j``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc import compiled, rotations
from ivc.dipole import kernels as _kernels
from ivc.dipole import numpy_kernels
from ivc.errors import InputError

FloatArray = NDArray[np.float64]


def flat_batch(a: ArrayLike, tail: tuple[int, ...], name: str) -> tuple[FloatArray, tuple[int, ...]]:
    """C-contiguous float64 view of ``a`` flattened to ``(M, *tail)``, and its leading shape."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape[a.ndim - len(tail) :] != tail or a.ndim < len(tail):
        raise InputError(f"{name} must have shape (..., {', '.join(map(str, tail))}), got {a.shape}")
    lead = a.shape[: a.ndim - len(tail)]
    return np.ascontiguousarray(a.reshape((-1, *tail))), lead


def flat_poses(r: ArrayLike, T: ArrayLike) -> tuple[FloatArray, FloatArray, tuple[int, ...]]:
    """Positions r (..., 3) and orientations T (..., 3, 3) broadcast against each other and flattened
    (:func:`flat_batch`) to (M, 3) and (M, 3, 3), and their common leading shape."""
    r_flat, lead = flat_batch(r, (3,), "r")
    T_flat, lead_T = flat_batch(T, (3, 3), "T")
    if lead != lead_T:
        r_b, T_b = np.broadcast_arrays(np.asarray(r, float)[..., None, :], np.asarray(T, float))
        r_flat, lead = flat_batch(r_b[..., 0, :], (3,), "r")
        T_flat, _ = flat_batch(T_b, (3, 3), "T")
    return r_flat, T_flat, lead


def field(r: ArrayLike) -> FloatArray:
    """Dipole coupling matrix ``f_D(r) = (3 r rᵀ / |r|² − I) / |r|³`` (eq. 72).

    Parameters
    ----------
    r : array, shape (..., 3)
        Sensor positions in the source frame, metres.

    Returns
    -------
    array, shape (..., 3, 3)
        Column ``j`` is the field at ``r`` of a unit dipole along source axis ``j``
        (normalised units, 1/m³). Symmetric and traceless; ``f_D(−r) = f_D(r)``.
        At ``r = 0`` the entries are not finite.

    Examples
    --------
    >>> field([1.0, 0.0, 0.0])
    array([[ 2.,  0.,  0.],
           [ 0., -1.,  0.],
           [ 0.,  0., -1.]])
    """
    flat, lead = flat_batch(r, (3,), "r")
    out = np.empty((flat.shape[0], 3, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        compiled.choose(_kernels.field_kernel, len(flat), compiled.VECTORISED, numpy_kernels.field_kernel)(flat, out)
    return out.reshape(lead + (3, 3))


def field_jacobian(r: ArrayLike) -> FloatArray:
    """Analytic derivative of ``f_D`` with respect to position.

    Returns ``J`` of shape ``(..., 3, 3, 3)`` with ``J[..., i, j, k] = ∂f_D[i, j] / ∂r_k``
    (1/m⁴)::

        ∂f_ij/∂r_k = 3 (δ_ik r_j + r_i δ_jk + δ_ij r_k) / |r|⁵ − 15 r_i r_j r_k / |r|⁷
    """
    r = np.asarray(r, dtype=float)
    if r.shape[-1:] != (3,):
        raise InputError(f"r must have shape (..., 3), got {r.shape}")
    rho2 = np.einsum("...i,...i->...", r, r)[..., None, None, None]
    eye = np.eye(3)
    sym = (
        np.einsum("ik,...j->...ijk", eye, r)
        + np.einsum("jk,...i->...ijk", eye, r)
        + np.einsum("ij,...k->...ijk", eye, r)
    )
    cubic = np.einsum("...i,...j,...k->...ijk", r, r, r)
    return (3.0 * sym - 15.0 * cubic / rho2) / rho2**2.5


def signal(r: ArrayLike, T: ArrayLike, G: ArrayLike | None = None) -> FloatArray:
    """Signal matrix ``S = Tᵀ (f_D(r) + G)`` (eq. 73).

    Parameters
    ----------
    r : array, shape (..., 3)
        Sensor positions, metres, source frame.
    T : array, shape (..., 3, 3)
        Sensor orientations: columns are the sensor axes in the source frame.
    G : array, shape (..., 3, 3), optional
        Secondary field in the source frame, same units as ``f_D`` (0 in free space).

    Returns
    -------
    array, shape (..., 3, 3)
    """
    r_flat, T_flat, lead = flat_poses(r, T)
    out = np.empty((r_flat.shape[0], 3, 3))
    compiled.choose(_kernels.signal_kernel, len(r_flat), compiled.VECTORISED, numpy_kernels.signal_kernel)(
        r_flat, T_flat, out)
    out = out.reshape(lead + (3, 3))
    if G is not None:
        T_full = T_flat.reshape(lead + (3, 3))
        out += np.swapaxes(T_full, -1, -2) @ np.asarray(G, dtype=float)
    return out


def signal_from_pose(position: ArrayLike, quaternion: ArrayLike) -> FloatArray:
    """Rebuild the signal matrix from a reported pose: ``S = QtoT(q)ᵀ f_D(r)`` (docs/math.md §9).

    For trackers that report poses only: if the unit's own solver inverts the dipole
    model, this is the signal it measured (up to the hemisphere sign of ``r``).
    """
    return signal(position, rotations.to_matrix(quaternion))
