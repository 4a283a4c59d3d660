"""Rotations: quaternions and rotation matrices, one convention everywhere.

Conventions (docs/conventions.md):

* A quaternion is ``[w, x, y, z]``: scalar first, Hamilton product, unit norm,
  canonical sign ``w >= 0`` (see :func:`canonical` for rotations by pi).
* ``to_matrix(q)`` (Himberg 2010's ``QtoT``) is the rotation matrix ``T`` whose columns
  are the sensor's axes written in the source frame, so ``T`` maps sensor-frame
  vectors into the source frame, and ``to_matrix(p ⊗ q) = to_matrix(p) @ to_matrix(q)``.
* scipy's ``Rotation`` is scalar-last; :func:`to_scipy` and :func:`from_scipy`
  are the only places that convert.

Every function is batched over leading axes: a quaternion array has shape
``(..., 4)``, a matrix array ``(..., 3, 3)``, a vector array ``(..., 3)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


#: below this, a component counts as zero when choosing the canonical sign
_SIGN_TOLERANCE = 1e-12


def canonical(q: ArrayLike) -> FloatArray:
    """Normalise quaternions to unit norm and choose the sign with ``w >= 0``.

    For rotations by pi (``|w|`` below 1e-12) ``w >= 0`` does not fix the sign: then the
    first of x, y, z that is not (numerically) zero is made positive, so that ``q`` and
    ``−q`` of one rotation always map to the same quaternion.
    """
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    significant = np.abs(q) > _SIGN_TOLERANCE
    first = np.argmax(significant, axis=-1)[..., None]
    deciding = np.take_along_axis(q, first, axis=-1)
    return np.where(deciding < 0.0, -q, q)


def multiply(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """Hamilton product ``p ⊗ q`` (broadcast over leading axes); not re-canonicalised."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def conjugate(q: ArrayLike) -> FloatArray:
    """Quaternion conjugate ``[w, -x, -y, -z]``: the inverse of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def to_matrix(q: ArrayLike) -> FloatArray:
    """Rotation matrix ``T = QtoT(q)`` of unit quaternions, shape ``(..., 3, 3)``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
        [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
        [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def from_matrix(T: ArrayLike) -> FloatArray:
    """Canonical unit quaternions (``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    Shepperd's method: the quaternion component of largest magnitude is taken from
    the diagonal and the others from off-diagonal sums, which keeps full precision
    for every rotation angle including pi.
    """
    T = np.asarray(T, dtype=float)
    t00, t11, t22 = T[..., 0, 0], T[..., 1, 1], T[..., 2, 2]
    d21, d02, d10 = T[..., 2, 1] - T[..., 1, 2], T[..., 0, 2] - T[..., 2, 0], T[..., 1, 0] - T[..., 0, 1]
    s01, s02, s12 = T[..., 0, 1] + T[..., 1, 0], T[..., 0, 2] + T[..., 2, 0], T[..., 1, 2] + T[..., 2, 1]
    squares = np.stack(
        [1.0 + t00 + t11 + t22, 1.0 + t00 - t11 - t22, 1.0 - t00 + t11 - t22, 1.0 - t00 - t11 + t22],
        axis=-1,
    )
    largest = np.argmax(squares, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        big = 0.5 * np.sqrt(np.maximum(np.take_along_axis(squares, largest[..., None], -1)[..., 0], 0.0))
        k = 0.25 / big
        candidates = np.stack(
            [
                np.stack([big, d21 * k, d02 * k, d10 * k], axis=-1),
                np.stack([d21 * k, big, s01 * k, s02 * k], axis=-1),
                np.stack([d02 * k, s01 * k, big, s12 * k], axis=-1),
                np.stack([d10 * k, s02 * k, s12 * k, big], axis=-1),
            ],
            axis=-2,
        )
    q = np.take_along_axis(candidates, largest[..., None, None], axis=-2)[..., 0, :]
    return canonical(q)


def rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Rotate vectors ``v`` (..., 3) by unit quaternions ``q`` (..., 4): ``QtoT(q) @ v``."""
    return np.einsum("...ij,...j->...i", to_matrix(q), np.asarray(v, dtype=float))


def angle(q: ArrayLike) -> FloatArray:
    """Rotation angle in radians, in ``[0, pi]``, of unit quaternions; stable at 0 and pi."""
    q = np.asarray(q, dtype=float)
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0]))


def angle_between(qa: ArrayLike, qb: ArrayLike) -> FloatArray:
    """Angle in radians of the rotation taking orientation ``qb`` to ``qa``."""
    return angle(multiply(qa, conjugate(qb)))


def angle_between_matrices(Ta: ArrayLike, Tb: ArrayLike) -> FloatArray:
    """Angle in radians of ``Ta @ Tb.T`` (docs/math.md §1's orientation error).

    ``atan2(sin, cos)`` with ``sin`` from the skew part and ``cos`` from the trace is
    accurate to rounding at every angle, where ``arccos((tr - 1) / 2)`` alone loses
    half the digits near 0 and pi.
    """
    R = np.einsum("...ij,...kj->...ik", np.asarray(Ta, dtype=float), np.asarray(Tb, dtype=float))
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin, cos)


def mean(q: ArrayLike, weights: ArrayLike | None = None, axis: int = 0) -> FloatArray:
    """Chordal L2 mean of orientations along ``axis``.

    The mean is the principal eigenvector of ``sum_i w_i q_i q_iᵀ`` (Markley et al.
    2007), which is insensitive to each quaternion's sign and, unlike averaging Euler
    angles, exact for any spread. Returns canonical quaternions with ``axis`` removed.
    """
    q = np.moveaxis(np.asarray(q, dtype=float), axis, -2)
    w = np.ones(q.shape[:-1]) if weights is None else np.moveaxis(np.asarray(weights, dtype=float), axis, -1)
    M = np.einsum("...n,...ni,...nj->...ij", w, q, q)
    _, vectors = np.linalg.eigh(M)
    return canonical(vectors[..., :, -1])


def random(shape: int | tuple[int, ...], rng: np.random.Generator | int | None = None) -> FloatArray:
    """Uniformly distributed random rotations as canonical quaternions, ``(*shape, 4)``."""
    rng = np.random.default_rng(rng)
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    return canonical(rng.standard_normal(shape + (4,)))


def from_rotvec(v: ArrayLike) -> FloatArray:
    """Quaternions of rotation vectors ``v`` (axis times angle in radians), ``(..., 3)``."""
    v = np.asarray(v, dtype=float)
    theta = np.linalg.norm(v, axis=-1, keepdims=True)
    # sin(theta/2)/theta, written with np.sinc so that it is exact at theta = 0
    scale = 0.5 * np.sinc(theta / (2.0 * np.pi))
    return np.concatenate([np.cos(0.5 * theta), scale * v], axis=-1)


def to_rotvec(q: ArrayLike) -> FloatArray:
    """Rotation vectors (axis times angle, ``|v| <= pi``) of unit quaternions."""
    q = canonical(q)
    half = np.arctan2(np.linalg.norm(q[..., 1:], axis=-1, keepdims=True), q[..., :1])
    scale = np.where(half > 1e-300, 2.0 * half / np.maximum(np.sin(half), 1e-300), 2.0)
    return scale * q[..., 1:]


def nearest_rotation(M: ArrayLike) -> FloatArray:
    """Nearest rotation matrix (Frobenius norm) to each ``(..., 3, 3)`` matrix, by SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def to_scipy(q: ArrayLike) -> Rotation:
    """scipy ``Rotation`` of scalar-first quaternions (scipy itself is scalar-last)."""
    return Rotation.from_quat(np.asarray(q, dtype=float), scalar_first=True)


def from_scipy(rotation: Rotation) -> FloatArray:
    """Canonical scalar-first quaternions of a scipy ``Rotation``."""
    return canonical(rotation.as_quat(scalar_first=True))
