"""Corrected poses from reported poses alone: the inverse of the tracker's pose-domain distortion.

A rotation-equivariant tracker reports ``v = φ(r)`` and ``Q = C(r) T`` for a sensor at ``(r, T)``,
with ``(φ, C)`` its solver applied to ``f_D + g`` (:mod:`ivc.pose.tracker_solver`). With the
table's ``g``, the correction ``r = φ⁻¹(v)``, ``T = C(r)ᵀ Q`` is exact: no signal is rebuilt and
no signal residual is asked for. Same :class:`~ivc.correct.solver.Correction` and flags as the
signal path, with these meanings:

``OUTSIDE``        the corrected position is outside the table's mapped volume
``NOT_CONVERGED``  the inversion did not reproduce the reported position to ``tolerance``
``HIGH_RESIDUAL``  the map does not produce the reported position, or not uniquely: the nearest
                   the inversion got, ``residual`` = |v − φ(r)| (m), is above ``max_residual``
                   (another room, a moved source, another hemisphere), or two distinct mapped
                   true positions produce it (see below)
``INVALID_INPUT``  the reported pose is not finite, or the sample was marked invalid

Where the inversion starts: at the reported position itself (a stream's sensor: moved by its
previous correction). Next to metal the map can send two distant true regions to the same
reported positions (measured on the default scene: about 0.2 % of the check poses), and pose-only
data cannot tell them apart. So each sample is also inverted from its nearest probe of a
:class:`SeedMap` (``φ`` and ``(∂φ/∂r)⁻¹`` tabulated at probe points over the mapped volume, the
table's grid refined twice), and from that probe's *partner* when its image lies among the
images of a distant region; when two starts give distinct mapped solutions the pose is
ambiguous and flagged HIGH_RESIDUAL (a reported pose the map does not produce uniquely). A
stream's continuing track skips that test: its history says which branch it is on.

For the closed-form tracker solver a compiled kernel does the inversion; for the
least-squares solver, :func:`ivc.pose.reported.invert_distortion` (NumPy) does.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ivc import compiled, rotations
from ivc.correct import reported_kernels as _pose_kernels
from ivc.correct.solver import HIGH_RESIDUAL, INVALID_INPUT, Correction
from ivc.dipole.pose import hemisphere_vector
from ivc.errors import InputError
from ivc.pose.reported import invert_distortion
from ivc.pose.tracker_solver import check_solver, distortion
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

#: the inversion stops when it reproduces the reported position to this (m)
TOLERANCE = 1e-11
#: HIGH_RESIDUAL above this miss of the reported position (m)
MAX_RESIDUAL_M = 1e-6
MAX_ITERATIONS = 40
#: two solutions farther apart than this (m) make a reported pose ambiguous
AMBIGUITY = 1e-3
#: probes per table cell edge
SUBDIVISION = 2


class SeedMap:
    """Where to start inverting ``φ``: probe points ``P`` (M, 3) m over the mapped volume, their images
    ``φ(P)`` (M, 3), inverse Jacobians ``(∂φ/∂r)⁻¹`` (M, 3, 3) (central differences), and for each probe
    the index of a distant probe whose image lies near its own (−1: none), see the module docstring."""

    def __init__(self, field: GridField, solver: str = "closed-form", hemisphere: str = "+x",
                 subdivision: int = SUBDIVISION):
        grid = field.grid
        self.spacing = grid.spacing / subdivision
        axes = [grid.origin[a] + self.spacing * np.arange((grid.shape[a] - 1) * subdivision + 1) for a in range(3)]
        fine = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        probes = fine[field.evaluate(fine)[2]]
        if len(probes) == 0:
            raise InputError("the table has no mapped cell to correct in")

        def phi(points):
            return distortion(points, field.evaluate(points)[0], solver=solver, hemisphere=hemisphere)[0]

        h = 1e-5
        J = np.empty((len(probes), 3, 3))
        for k in range(3):
            step = np.zeros(3)
            step[k] = h
            J[..., k] = (phi(probes + step) - phi(probes - step)) / (2 * h)
        images = phi(probes)
        good = np.all(np.isfinite(images), axis=1) & np.all(np.isfinite(J.reshape(-1, 9)), axis=1)
        good &= np.abs(np.linalg.det(np.where(good[:, None, None], J, np.eye(3)))) > 1e-6
        self.probes, self.images, J = probes[good], images[good], J[good]
        self.inverse = np.linalg.inv(J)
        self.tree = cKDTree(self.images)
        # a probe's image neighbourhood: one probe spacing, stretched as the map stretches it there
        stretch = np.linalg.norm(J, ord=2, axis=(1, 2))
        radius = stretch * self.spacing
        self.partner = np.full(len(self.probes), -1)
        near = self.tree.query_ball_point(self.images, radius)
        counts = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
        i = np.repeat(np.arange(len(near)), counts)
        j = np.fromiter((k for n in near for k in n), dtype=np.int64, count=int(counts.sum()))
        apart = self.probes[j] - self.probes[i]
        linear = np.einsum("nij,nj->ni", self.inverse[i], self.images[j] - self.images[i])
        distance = np.linalg.norm(apart, axis=1)
        # another branch: far apart, and not where the local linear map puts it
        far = (distance > 2 * self.spacing) & (np.linalg.norm(apart - linear, axis=1) > 0.5 * distance)
        i, j = i[far], j[far]
        if len(i):
            order = np.lexsort((np.linalg.norm(self.images[j] - self.images[i], axis=1), i))
            i, j = i[order], j[order]
            first = np.r_[True, i[1:] != i[:-1]]  # per probe, its partner with the nearest image
            self.partner[i[first]] = j[first]
        self.reach = 4.0 * self.spacing * max(float(np.max(stretch)), 1.0)

    @property
    def ambiguous_fraction(self) -> float:
        """Share of the probes whose images overlap those of a distant region."""
        return float(np.mean(self.partner >= 0))

    def starts(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For reported positions v (n, 3): start (n, 3) and H (n, 3, 3) from the nearest probe image, and the
        partner's start and H (NaN and I where there is none). Far from every image: v and I."""
        n = len(v)
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        distance, index = self.tree.query(np.where(np.isfinite(v), v, 0.0))
        near = np.isfinite(distance) & (distance <= self.reach) & np.all(np.isfinite(v), axis=1)
        index = np.where(near, index, 0)

        def from_probe(i):
            H = self.inverse[i]
            return self.probes[i] + np.einsum("nij,nj->ni", H, v - self.images[i]), H

        start, H = from_probe(index)
        start = np.where(near[:, None], start, v)
        H = np.where(near[:, None, None], H, eye)
        partner = np.where(near, self.partner[index], -1)
        has = partner >= 0
        p_start, p_H = from_probe(np.where(has, partner, 0))
        p_start = np.where(has[:, None], p_start, np.nan)
        p_H = np.where(has[:, None, None], p_H, eye)
        return np.ascontiguousarray(start), np.ascontiguousarray(H), np.ascontiguousarray(p_start), \
            np.ascontiguousarray(p_H)


def table_solver(table: LookupTable) -> str:
    """The tracker solver a table was fitted for (``closed-form`` for tables fitted from signals)."""
    return str(table.fit.get("tracker_solver", "closed-form"))


class PoseCorrector:
    """Applies a table to reported poses: :meth:`batch` for arrays of frames, :meth:`update` for a stream.

    ``solver``: the tracker's pose solver (default: the one the table was fitted for, else
    ``closed-form``). ``hemisphere``: default the table's. ``max_residual``: the HIGH_RESIDUAL
    threshold in metres. ``check_ambiguity``: also invert each sample (not a stream's continuing
    track) from its nearest probe and that probe's partner, and flag distinct mapped solutions.
    """

    def __init__(self, table: LookupTable | GridField, hemisphere: str | None = None, interpolation: str = "cubic",
                 solver: str | None = None, max_residual: float = MAX_RESIDUAL_M,
                 max_iterations: int = MAX_ITERATIONS, tolerance: float = TOLERANCE, check_ambiguity: bool = True):
        self.field = table.field(interpolation) if isinstance(table, LookupTable) else table
        if solver is None:
            solver = table_solver(table) if isinstance(table, LookupTable) else "closed-form"
        self.solver = check_solver(solver)
        self.hemisphere = hemisphere or (table.hemisphere if isinstance(table, LookupTable) else "+x")
        self._h = hemisphere_vector(self.hemisphere)
        if not max_residual > 0:
            raise InputError(f"max_residual must be positive (metres), got {max_residual}")
        self.max_residual = float(max_residual)
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        # per sensor (row ``_slot[key]``): the previous good correction offset r − v, and whether it is current
        self._slot: dict = {}
        self._slot_cache: dict = {}
        self._offset = np.zeros((16, 3))
        self._tracked = np.zeros(16, dtype=bool)
        self._seeds: SeedMap | None = None
        self.check_ambiguity = bool(check_ambiguity)

    def _secondary(self, r: np.ndarray) -> np.ndarray:
        return self.field.evaluate(r)[0]

    @property
    def seeds(self) -> SeedMap:
        """The probe map the inversions start from (built on first use)."""
        if self._seeds is None:
            # starts only: the closed form's map is close to any equivariant solver's and far cheaper
            self._seeds = SeedMap(self.field, "closed-form", self.hemisphere)
        return self._seeds

    def _invert(self, v, start, H, serial):
        n = len(v)
        if self.solver == "closed-form":
            f = self.field
            r, C = np.empty((n, 3)), np.empty((n, 3, 3))
            miss, converged = np.empty(n), np.empty(n, dtype=bool)
            iterations, mapped = np.empty(n, dtype=np.int64), np.empty(n, dtype=bool)
            kernel = compiled.choose(_pose_kernels.invert_serial if serial else _pose_kernels.invert_kernel, n)
            kernel(v, start, H.copy(), self._h, f.kernel_grid, self.max_iterations, self.tolerance, r, C, miss,
                   converged, iterations, mapped)
            return r, C, miss, converged, iterations, mapped
        inv = invert_distortion(v, self._secondary, self.solver, self.hemisphere, start, self.tolerance,
                                self.max_iterations)
        ok = np.all(np.isfinite(inv.position), axis=1)
        mapped = self.field.evaluate(np.where(ok[:, None], inv.position, 0.0))[2] & ok
        return inv.position, inv.turn, inv.miss, inv.converged, inv.iterations, mapped

    def _run(self, v: np.ndarray, Q: np.ndarray, previous: np.ndarray, serial: bool) -> Correction:
        """Correct reported positions v (n, 3) and rotations Q (n, 3, 3); ``previous`` (n, 3): each sample's
        previous good correction offset r − v (NaN: none), which then starts the inversion."""
        n = len(v)
        finite = np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(Q.reshape(n, 9)), axis=1)
        v = np.ascontiguousarray(np.where(finite[:, None], v, 1.0))
        tracked = np.all(np.isfinite(previous), axis=1)
        start = np.where(tracked[:, None], v + np.where(tracked[:, None], previous, 0.0), v)
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        r, C, miss, converged, iterations, mapped = self._invert(v, start, eye, serial)
        ambiguous = np.zeros(n, dtype=bool)
        check = np.flatnonzero(finite & ~tracked) if self.check_ambiguity else np.zeros(0, int)
        if len(check):  # a stream's continuing track needs no other start: its history tells which branch
            p_start, p_H, q_start, q_H = self.seeds.starts(v[check])
            other = [(check, p_start, p_H)]
            has = np.all(np.isfinite(q_start), axis=1)
            if has.any():
                other.append((check[has], q_start[has], q_H[has]))
            for idx, s0, H0 in other:
                r2, C2, miss2, conv2, it2, mapped2 = self._invert(v[idx], s0, H0, serial)
                good1 = converged[idx] & mapped[idx]
                good2 = conv2 & mapped2
                # a second solution elsewhere makes the pose ambiguous; where the first start failed, another
                # start's solution is not taken either (measured: it is most often the wrong branch)
                ambiguous[idx] |= good1 & good2 & (np.linalg.norm(r[idx] - r2, axis=1) > AMBIGUITY)
                iterations[idx] += it2
        q, flags = np.empty((n, 4)), np.empty(n, dtype=np.uint8)
        contiguous = np.ascontiguousarray
        compose = compiled.choose(_pose_kernels.compose_kernel, n)
        compose(contiguous(C, dtype=float), contiguous(Q, dtype=float),
                contiguous(mapped, dtype=bool), contiguous(converged, dtype=bool),
                contiguous(miss, dtype=float), self.max_residual, q, flags)
        flags[ambiguous] |= HIGH_RESIDUAL
        flags[~finite] = INVALID_INPUT
        r[~finite], q[~finite], miss[~finite], iterations[~finite] = np.nan, np.nan, np.nan, 0
        return Correction(r, q, flags, miss, iterations)

    def invert_from_probes(self, position: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Invert ``φ`` at reported positions (n, 3) m from each one's nearest probe of :attr:`seeds` rather than
        from the position itself: (true positions (n, 3) m, whether each reproduces its reported position to
        ``max_residual``, whether it is in the mapped volume). No ambiguity test: a start of last resort, for
        grids an export fills (ivc.export.distortion), never for trusting a measurement."""
        v = np.ascontiguousarray(np.asarray(position, float).reshape(-1, 3))
        start, H, _, _ = self.seeds.starts(v)
        r, _, miss, converged, _, mapped = self._invert(v, start, H, serial=False)
        return r, converged & (miss <= self.max_residual), mapped

    def batch(self, position: np.ndarray, quaternion: np.ndarray, valid: np.ndarray | None = None) -> Correction:
        """Correct reported poses: positions (..., 3) m and quaternions (..., 4) [w, x, y, z], each sample on
        its own. Samples with ``valid`` False are flagged INVALID_INPUT. ``residual`` is |v − φ(r)| in m."""
        position, quaternion = np.asarray(position, float), np.asarray(quaternion, float)
        if position.shape[-1:] != (3,) or quaternion.shape != position.shape[:-1] + (4,):
            raise InputError(f"reported poses need positions (..., 3) and quaternions (..., 4) of the same leading "
                             f"shape, got {position.shape} and {quaternion.shape}")
        lead = position.shape[:-1]
        v = position.reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            Q = rotations.to_matrix(quaternion.reshape(-1, 4))
        if valid is not None:
            bad = ~np.asarray(valid, bool).reshape(-1)
            v = np.where(bad[:, None], np.nan, v)
        out = self._run(v, Q, np.full((len(v), 3), np.nan), serial=len(v) < 64)
        return Correction(out.position.reshape(*lead, 3), out.quaternion.reshape(*lead, 4), out.flags.reshape(lead),
                          out.residual.reshape(lead), out.iterations.reshape(lead))

    def update(self, position: np.ndarray, rotation: np.ndarray, sensors: list | tuple | None = None) -> Correction:
        """Correct the latest frame of a stream: positions (N, 3) m and rotation matrices (N, 3, 3), one per
        sensor. Each sensor starts from its reported position moved by its own previous good correction
        (keyed by ``sensors``, default 0..N−1), or from the reported position.

        For the closed-form solver, a frame whose sensors all continue a track (or any frame without the
        ambiguity test) is corrected by one compiled call (:func:`ivc.correct.reported_kernels.stream_kernel`),
        the same steps as :meth:`batch` from another start; other frames go through the batch's path.
        """
        v = np.ascontiguousarray(np.asarray(position, dtype=float).reshape(-1, 3))
        Q = np.ascontiguousarray(np.asarray(rotation, dtype=float).reshape(-1, 3, 3))
        if len(Q) != len(v):
            raise InputError(f"a frame needs one rotation per position, got {len(v)} positions and {len(Q)} rotations")
        slots = self._slots(sensors, len(v))
        if self.solver == "closed-form" and (not self.check_ambiguity or self._tracked[slots].all()):
            n = len(v)
            r, q, flags = np.empty((n, 3)), np.empty((n, 4)), np.empty(n, dtype=np.uint8)
            miss, iterations = np.empty(n), np.empty(n, dtype=np.int64)
            f = self.field
            stream = compiled.choose(_pose_kernels.stream_kernel, n)
            stream(v, Q, slots, self._offset, self._tracked, self._h, f.kernel_grid, self.max_iterations,
                   self.tolerance, self.max_residual, r, q, flags, miss, iterations)
            return Correction(r, q, flags, miss, iterations)
        tracked = self._tracked[slots]
        offsets = np.where(tracked[:, None], self._offset[slots], np.nan)
        out = self._run(v, Q, offsets, serial=True)
        for n, slot in enumerate(slots):  # in order, as the compiled path: a sensor named twice keeps its last
            self._tracked[slot] = out.flags[n] == 0
            if out.flags[n] == 0:
                self._offset[slot] = out.position[n] - v[n]
        return out

    def warm_starts(self, sensors: list | tuple | str) -> np.ndarray:
        """Each named sensor's current warm start for :meth:`update`: its previous good correction offset
        ``r − v`` (n, 3) m, NaN where it has none (a new sensor, after a flagged sample or :meth:`reset`)."""
        slots = self._slots(sensors, len(tuple(sensors)))
        return np.where(self._tracked[slots][:, None], self._offset[slots], np.nan)

    def correct_from(self, position: np.ndarray, rotation: np.ndarray, offsets: np.ndarray) -> Correction:
        """The batch's path for reported positions (n, 3) m and rotations (n, 3, 3), each sample started at
        ``position + offsets`` ((n, 3) m; a NaN row: at the position, with the ambiguity test), without touching
        any sensor's warm start: what :meth:`update` computes for a frame, in the batch's steps."""
        v = np.ascontiguousarray(np.asarray(position, dtype=float).reshape(-1, 3))
        Q = np.asarray(rotation, dtype=float).reshape(-1, 3, 3)
        offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
        if not len(v) == len(Q) == len(offsets):
            raise InputError(f"{len(v)} positions, {len(Q)} rotations and {len(offsets)} offsets: give one each")
        return self._run(v, Q, offsets, serial=True)

    def warm_up(self, position: np.ndarray) -> None:
        """Run the compiled steps of :meth:`batch` and :meth:`update` once, at a reported position (3,) m, so
        that a stream's first frames do not wait for them; no sensor's warm start is touched."""
        v = np.asarray(position, dtype=float).reshape(1, 3)
        Q = np.eye(3)[None]
        self.correct_from(v, Q, np.zeros((1, 3)))
        if self.solver == "closed-form":
            out = [np.empty((1, 3)), np.empty((1, 4)), np.empty(1, dtype=np.uint8), np.empty(1),
                   np.empty(1, dtype=np.int64)]
            _pose_kernels.stream_kernel(np.ascontiguousarray(v), Q, np.zeros(1, dtype=np.int64), np.zeros((1, 3)),
                                        np.ones(1, dtype=bool), self._h, self.field.kernel_grid,
                                        self.max_iterations, self.tolerance, self.max_residual, *out)

    def _slots(self, sensors, n: int) -> np.ndarray:
        """Rows of the warm-start arrays (``_offset``, ``_tracked``) of the frame's sensors, added on first use."""
        keys = tuple(range(n)) if sensors is None else tuple(sensors)
        slots = self._slot_cache.get(keys)
        if slots is not None:
            return slots
        if len(keys) != n:
            raise InputError(f"{len(keys)} sensor names for a frame of {n} samples")
        for key in keys:
            if key not in self._slot:
                self._slot[key] = len(self._slot)
        if len(self._slot) > len(self._tracked):
            grow = max(len(self._slot), 2 * len(self._tracked))
            self._offset = np.vstack([self._offset, np.zeros((grow - len(self._offset), 3))])
            self._tracked = np.concatenate([self._tracked, np.zeros(grow - len(self._tracked), dtype=bool)])
        slots = np.array([self._slot[k] for k in keys], dtype=np.int64)
        if len(self._slot_cache) < 1024:
            self._slot_cache[keys] = slots
        return slots

    def reset(self) -> None:
        """Forget every sensor's warm start (after a gap in the stream)."""
        self._tracked[:] = False
