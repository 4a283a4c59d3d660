"""Eddy currents in thin conductors: the stream-function method on triangle meshes.

The surface current on a conductor is ``K = ∇ψ × n̂`` for a stream function ψ that is
piecewise linear on the mesh (one unknown per free vertex; the hat function of vertex
``i`` is a small current loop around it). A stream function is a dipole layer of
density ``ψ n̂``, so its magnetic moment is ``∫ ψ n̂ dA``. This is the method
bfieldtools implements (Mäkinen et al. 2020; Zetter et al. 2020), written here on
numpy and trimesh.

Units are the ones of ``ivc.dipole``: fields are normalised by ``μ0 m / 4π`` (``m``
the source coil moment), so the primary field of source coil ``j`` at ``x`` is column
``j`` of ``f_D(x)``, and inductances are divided by ``μ0 / 4π``. The circuit equation
for the three source coils at angular frequency ω is then

    (R + jκ L') ψ = −jκ Φ',        κ = ω μ0 / 4π

with ``L'_ij = ∫∫ J_i·J_j / |r − r'|`` (J_i the current density of hat function i),
``R_ij = ∫ J_i·J_j / (σ t)``, and ``Φ'_ij = ∫ φ_i (f_D e_j)·n̂`` the primary flux
through hat function i. The perfect-conductor limit is ``L' ψ = −Φ'``. The tracker's
synchronous detector sees the in-phase (real) part of the secondary field.

Approximations (documented in docs/simulator.md):

* thin sheets: currents are surface currents; a closed solid carries them in a skin of
  thickness ``min(thickness, skin depth)``;
* the inductance integral ``∫_f ∫_g 1/R`` is exact (analytic inner integral,
  7-point outer quadrature) for nearby triangle pairs, where it matters most, and a
  centroid rule for distant ones;
* the secondary field is evaluated from one dipole per triangle (the dipole layer's
  moment ``A ψ̄ n̂`` at the centroid), accurate a few triangle sizes from the surface;
* open sheets have ψ = 0 on their boundary (no net current around holes); closed
  surfaces have one vertex per component fixed to remove the constant null mode.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.csgraph
import trimesh
from scipy.spatial import cKDTree

from ivc import dipole
from ivc.dipole.kernels import field_entries

#: Dunavant's degree-5 rule on a triangle: barycentric points and weights (sum 1)
_A1, _B1, _W1 = 0.059715871789770, 0.470142064105115, 0.132394152788506
_A2, _B2, _W2 = 0.797426985353087, 0.101286507323456, 0.125939180544827
QUAD_BARY = np.array(
    [[1 / 3, 1 / 3, 1 / 3], [_A1, _B1, _B1], [_B1, _A1, _B1], [_B1, _B1, _A1], [_A2, _B2, _B2], [_B2, _A2, _B2],
     [_B2, _B2, _A2]]
)
QUAD_WEIGHTS = np.array([0.225, _W1, _W1, _W1, _W2, _W2, _W2])

MU0_OVER_4PI = 1e-7
NEAR_FACTOR = 3.0  # triangle pairs closer than this many (summed) radii get the exact integral


def triangle_potential(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """``∫_T 1/|x − y| dA(y)`` over triangles ``tri`` (K, 3, 3) at points ``x`` (K, 3), exactly.

    The closed form of Wilton et al. (1984) / Graglia (1993): with ``h`` the height
    of x above the triangle's plane and, per edge, ``t0`` the in-plane distance to the
    edge's line, ``l±`` the distances along it to the edge ends and ``R±`` to the ends,
    ``I = Σ_edges t0 ln((R+ + l+)/(R− + l−)) − |h| [atan(t0 l+/(R0² + |h| R+)) − atan(t0 l−/(R0² + |h| R−))]``.
    """
    x = np.ascontiguousarray(x, dtype=float)
    tri = np.ascontiguousarray(tri, dtype=float)
    out = np.empty(len(x))
    _potential_kernel(x, tri, out)
    return out


@dataclass
class ConductorMesh:
    """All conductors of a scene as one mesh, with per-face surface resistivity 1/(σ t) in ohms."""

    vertices: np.ndarray  # (V, 3) metres
    faces: np.ndarray  # (F, 3) vertex indices, counter-clockwise about the normal
    surface_resistivity: np.ndarray  # (F,) ohms; 0 for a perfect conductor
    free: np.ndarray  # (V,) bool: vertices whose ψ is unknown

    @classmethod
    def from_parts(cls, parts: list[tuple[trimesh.Trimesh, float]]) -> ConductorMesh:
        """Join meshes, each with its surface resistivity, and choose the free vertices."""
        vertices, faces, rho, free, offset = [], [], [], [], 0
        for mesh, resistivity in parts:
            v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
            edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
            graph = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(v),) * 2)
            _, label = scipy.sparse.csgraph.connected_components(graph, directed=False)
            unique_edges, count = np.unique(edges, axis=0, return_counts=True)
            on_boundary = np.zeros(len(v), dtype=bool)
            on_boundary[unique_edges[count == 1].ravel()] = True
            is_free = ~on_boundary
            for component in np.unique(label[f[:, 0]]):
                members = np.flatnonzero(label == component)
                if not on_boundary[members].any():
                    is_free[members[0]] = False  # closed surface: a constant ψ carries no current
            used = np.zeros(len(v), dtype=bool)
            used[f.ravel()] = True
            vertices.append(v)
            faces.append(f + offset)
            rho.append(np.full(len(f), resistivity))
            free.append(is_free & used)
            offset += len(v)
        return cls(np.concatenate(vertices), np.concatenate(faces), np.concatenate(rho), np.concatenate(free))

    @cached_property
    def corners(self) -> np.ndarray:
        return self.vertices[self.faces]  # (F, 3, 3)

    @cached_property
    def areas(self) -> np.ndarray:
        c = self.corners
        return 0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)

    @cached_property
    def normals(self) -> np.ndarray:
        c = self.corners
        n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    @cached_property
    def centroids(self) -> np.ndarray:
        return self.corners.mean(axis=1)


def _current_matrices(mesh: ConductorMesh) -> list[scipy.sparse.csr_matrix]:
    """Per axis a, the (F, V) matrix of the a-component of J_i on face f.

    On face (a, b, c), counter-clockwise, hat function i carries the uniform current
    density ``J = (opposite edge, walked counter-clockwise) / (2 A)``.
    """
    c = mesh.corners
    two_area = 2.0 * mesh.areas
    edges = [c[:, 2] - c[:, 1], c[:, 0] - c[:, 2], c[:, 1] - c[:, 0]]  # opposite to corner 0, 1, 2
    rows = np.repeat(np.arange(len(c)), 3)
    cols = mesh.faces.ravel()
    out = []
    for axis in range(3):
        values = np.stack([e[:, axis] / two_area for e in edges], axis=1).ravel()
        out.append(scipy.sparse.csr_matrix((values, (rows, cols)), shape=(len(c), len(mesh.vertices))))
    return out


def face_integral_matrix(mesh: ConductorMesh) -> np.ndarray:
    """``P_fg = ∫_f ∫_g 1/|r − r'| dA dA'`` for all triangle pairs (F, F), symmetric."""
    centroids, areas = mesh.centroids, mesh.areas
    radii = np.linalg.norm(mesh.corners - centroids[:, None], axis=2).max(axis=1)
    F = len(areas)
    P = np.empty((F, F))
    _centroid_rule_kernel(centroids, areas, P)
    tree = cKDTree(centroids)
    pairs = tree.query_pairs(NEAR_FACTOR * 2 * radii.max(), output_type="ndarray")
    d = np.linalg.norm(centroids[pairs[:, 0]] - centroids[pairs[:, 1]], axis=1)
    pairs = pairs[d < NEAR_FACTOR * (radii[pairs[:, 0]] + radii[pairs[:, 1]])]
    near = np.concatenate([pairs, pairs[:, ::-1], np.repeat(np.arange(F), 2).reshape(-1, 2)])
    f, g = np.ascontiguousarray(near[:, 0]), np.ascontiguousarray(near[:, 1])  # one layout: one compile
    values = np.empty(len(near))
    _near_pair_kernel(np.ascontiguousarray(mesh.corners), f, g, QUAD_BARY, QUAD_WEIGHTS, values)
    P[f, g] = values
    P += P.T
    P *= 0.5
    return P


def inductance_matrix(mesh: ConductorMesh) -> np.ndarray:
    """``L'_ij = Σ_fg J_i^f · J_j^g P_fg`` (henry / (μ0/4π), i.e. metres), over all vertices (V, V)."""
    P = face_integral_matrix(mesh)
    L = np.zeros((len(mesh.vertices),) * 2)
    for C in _current_matrices(mesh):
        CtP = np.asarray(C.T @ P)  # (V, F)
        L += np.asarray(C.T @ CtP.T).T  # = Cᵀ P C
    return 0.5 * (L + L.T)


def resistance_matrix(mesh: ConductorMesh) -> scipy.sparse.csr_matrix:
    """``R_ij = Σ_f (A_f / σt) J_i^f · J_j^f`` in ohms (V, V), sparse."""
    weight = scipy.sparse.diags(mesh.areas * mesh.surface_resistivity)
    return sum(C.T @ weight @ C for C in _current_matrices(mesh)).tocsr()


def primary_flux(mesh: ConductorMesh) -> np.ndarray:
    """``Φ'_ij = ∫ φ_i (f_D e_j)·n̂ dA``: flux of source coil j through hat function i (V, 3)."""
    corners, areas, normals = mesh.corners, mesh.areas, mesh.normals
    points = np.einsum("qk,nkj->nqj", QUAD_BARY, corners)  # (F, 7, 3)
    normal_field = np.einsum("nqij,ni->nqj", dipole.field(points), normals)  # (F, 7, 3): (f_D e_j)·n
    # corner k of face f gets Σ_q w_q bary_qk (B_j·n)(q) A_f
    per_corner = np.einsum("q,qk,nqj->nkj", QUAD_WEIGHTS, QUAD_BARY, normal_field) * areas[:, None, None]
    flux = np.zeros((len(mesh.vertices), 3))
    np.add.at(flux, mesh.faces.ravel(), per_corner.reshape(-1, 3))
    return flux


def solve_stream_function(mesh: ConductorMesh, frequency_hz: float) -> np.ndarray:
    """In-phase stream function ψ (V, 3) per source coil (normalised units, 0 at fixed vertices)."""
    L = inductance_matrix(mesh)
    flux = primary_flux(mesh)
    free = mesh.free
    psi = np.zeros((len(mesh.vertices), 3))
    Lf = L[np.ix_(free, free)]
    if np.all(mesh.surface_resistivity == 0):
        psi[free] = scipy.linalg.solve(Lf, -flux[free], assume_a="pos")
        return psi
    kappa = 2 * np.pi * frequency_hz * MU0_OVER_4PI
    R = resistance_matrix(mesh).toarray()[np.ix_(free, free)]
    complex_psi = scipy.linalg.solve(R + 1j * kappa * Lf, -1j * kappa * flux[free], assume_a="sym")
    psi[free] = complex_psi.real
    return psi


@dataclass
class FaceDipoles:
    """The secondary field of solved eddy currents as one dipole per triangle.

    ``moments[f, :, j]`` is the moment of face f's dipole for source coil j
    (normalised units, m³ scaled as in ``ivc.dipole``), placed at ``centres[f]``.
    """

    centres: np.ndarray  # (F, 3)
    moments: np.ndarray  # (F, 3, 3)

    @classmethod
    def from_solution(cls, mesh: ConductorMesh, psi: np.ndarray) -> FaceDipoles:
        mean_psi = psi[mesh.faces].mean(axis=1)  # (F, 3)
        moments = (mesh.areas[:, None] * mesh.normals)[:, :, None] * mean_psi[:, None, :]
        return cls(mesh.centroids, moments)

    def field(self, points: np.ndarray) -> np.ndarray:
        """Secondary field ``G`` (..., 3, 3) at ``points`` (..., 3): column j for source coil j."""
        points = np.asarray(points, float)
        flat = np.ascontiguousarray(points.reshape(-1, 3))
        out = np.empty((len(flat), 3, 3))
        _dipole_sum_kernel(flat, np.ascontiguousarray(self.centres), np.ascontiguousarray(self.moments), out)
        return out.reshape(points.shape[:-1] + (3, 3))


@numba.njit(parallel=True, cache=True, fastmath=True)
def _dipole_sum_kernel(points, centres, moments, out):  # pragma: no cover - compiled
    """out[m] = Σ_f f_D(points[m] − centres[f]) @ moments[f]."""
    for m in numba.prange(points.shape[0]):
        acc = np.zeros((3, 3))
        px, py, pz = points[m, 0], points[m, 1], points[m, 2]
        for f in range(centres.shape[0]):
            x = px - centres[f, 0]
            y = py - centres[f, 1]
            z = pz - centres[f, 2]
            f00, f11, f22, f01, f02, f12 = field_entries(x, y, z)
            for j in range(3):
                m0 = moments[f, 0, j]
                m1 = moments[f, 1, j]
                m2 = moments[f, 2, j]
                acc[0, j] += f00 * m0 + f01 * m1 + f02 * m2
                acc[1, j] += f01 * m0 + f11 * m1 + f12 * m2
                acc[2, j] += f02 * m0 + f12 * m1 + f22 * m2
        for i in range(3):
            for j in range(3):
                out[m, i, j] = acc[i, j]


@numba.njit(inline="always")
def _potential_one(x0, x1, x2, tri):
    """:func:`triangle_potential` of one triangle (3, 3) at one point (x0, x1, x2)."""
    e10, e11, e12 = tri[1, 0] - tri[0, 0], tri[1, 1] - tri[0, 1], tri[1, 2] - tri[0, 2]
    e20, e21, e22 = tri[2, 0] - tri[0, 0], tri[2, 1] - tri[0, 1], tri[2, 2] - tri[0, 2]
    n0, n1, n2 = e11 * e22 - e12 * e21, e12 * e20 - e10 * e22, e10 * e21 - e11 * e20
    nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
    h = (x0 - tri[0, 0]) * n0 + (x1 - tri[0, 1]) * n1 + (x2 - tri[0, 2]) * n2
    p0, p1, p2 = x0 - h * n0, x1 - h * n1, x2 - h * n2
    ah = abs(h)
    total = 0.0
    for k in range(3):
        a0, a1, a2 = tri[k, 0], tri[k, 1], tri[k, 2]
        b0, b1, b2 = tri[(k + 1) % 3, 0], tri[(k + 1) % 3, 1], tri[(k + 1) % 3, 2]
        d0, d1, d2 = b0 - a0, b1 - a1, b2 - a2
        length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        l0, l1, l2 = d0 / length, d1 / length, d2 / length
        u0, u1, u2 = l1 * n2 - l2 * n1, l2 * n0 - l0 * n2, l0 * n1 - l1 * n0
        t0 = (a0 - p0) * u0 + (a1 - p1) * u1 + (a2 - p2) * u2
        if abs(t0) <= 1e-12 * length:
            continue
        l_plus = (b0 - p0) * l0 + (b1 - p1) * l1 + (b2 - p2) * l2
        l_minus = (a0 - p0) * l0 + (a1 - p1) * l1 + (a2 - p2) * l2
        r_plus = np.sqrt((x0 - b0) ** 2 + (x1 - b1) ** 2 + (x2 - b2) ** 2)
        r_minus = np.sqrt((x0 - a0) ** 2 + (x1 - a1) ** 2 + (x2 - a2) ** 2)
        r0sq = t0 * t0 + h * h
        if l_plus + l_minus >= 0:
            log_term = np.log((r_plus + l_plus) / (r_minus + l_minus))
        else:
            log_term = np.log((r_minus - l_minus) / (r_plus - l_plus))
        atan_term = np.arctan(t0 * l_plus / (r0sq + ah * r_plus)) - np.arctan(t0 * l_minus / (r0sq + ah * r_minus))
        total += t0 * log_term - ah * atan_term
    return total


@numba.njit(parallel=True, cache=True)
def _potential_kernel(x, tri, out):  # pragma: no cover - compiled
    for k in numba.prange(x.shape[0]):
        out[k] = _potential_one(x[k, 0], x[k, 1], x[k, 2], tri[k])


@numba.njit(parallel=True, cache=True)
def _near_pair_kernel(corners, f, g, bary, weights, out):  # pragma: no cover - compiled
    """out[k] = A_f Σ_q w_q ∫_g 1/|x_q − y| dA(y), x_q the quadrature points of face f[k]."""
    for k in numba.prange(f.shape[0]):
        tf = corners[f[k]]
        tg = corners[g[k]]
        c0 = (tf[1, 1] - tf[0, 1]) * (tf[2, 2] - tf[0, 2]) - (tf[1, 2] - tf[0, 2]) * (tf[2, 1] - tf[0, 1])
        c1 = (tf[1, 2] - tf[0, 2]) * (tf[2, 0] - tf[0, 0]) - (tf[1, 0] - tf[0, 0]) * (tf[2, 2] - tf[0, 2])
        c2 = (tf[1, 0] - tf[0, 0]) * (tf[2, 1] - tf[0, 1]) - (tf[1, 1] - tf[0, 1]) * (tf[2, 0] - tf[0, 0])
        area = 0.5 * np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        acc = 0.0
        for q in range(weights.shape[0]):
            x0 = bary[q, 0] * tf[0, 0] + bary[q, 1] * tf[1, 0] + bary[q, 2] * tf[2, 0]
            x1 = bary[q, 0] * tf[0, 1] + bary[q, 1] * tf[1, 1] + bary[q, 2] * tf[2, 1]
            x2 = bary[q, 0] * tf[0, 2] + bary[q, 1] * tf[1, 2] + bary[q, 2] * tf[2, 2]
            acc += weights[q] * _potential_one(x0, x1, x2, tg)
        out[k] = area * acc


@numba.njit(parallel=True, cache=True)
def _centroid_rule_kernel(centroids, areas, out):  # pragma: no cover - compiled
    """out[f, g] = A_f A_g / |c_f − c_g| (the diagonal is overwritten by the exact self term)."""
    for f in numba.prange(centroids.shape[0]):
        for g in range(centroids.shape[0]):
            d = np.sqrt((centroids[f, 0] - centroids[g, 0]) ** 2 + (centroids[f, 1] - centroids[g, 1]) ** 2
                        + (centroids[f, 2] - centroids[g, 2]) ** 2)
            out[f, g] = areas[f] * areas[g] / d if d > 0 else 0.0
