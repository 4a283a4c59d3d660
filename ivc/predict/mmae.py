"""Kyger 1995: multiple-model adaptive estimation over Gauss-Markov look-vector filters.

Equations: docs/math.md §15.

Elemental filters share the per-axis state [position, velocity, acceleration] of a unit look
vector, measured with ``H = [1 0 0]`` per axis and ``R = r I3``:

* ``cp``: constant position, Qd = q Δt on position (``q`` in (unit/s)... per second);
* ``fogmv``: first-order Gauss-Markov velocity (Liang), σ² the velocity variance, τ its correlation time;
* ``fogma``: first-order Gauss-Markov acceleration (Singer), σ² the acceleration variance;
* ``phi2``: a FOGMA propagated by Φ(κΔt) inside its own recursion (Kyger's "Φ²" lead, κ = 2).

Φ and Qd come from Van Loan's matrix exponential, not the printed closed forms (docs/math.md §15.2:
q11 is misprinted and the closed form cancels catastrophically for τ ≫ Δt). The bank runs the
Bayesian probability recursion in the log domain with a lower bound, declares a filter
divergent when rᵀA⁻¹r exceeds its threshold (zero weight; its position reset to the blend of
the others; its probability to the bound), and predicts ``Σ w_j [Φ_j(δ) x̂_j]_position``.

Orientation streams: one bank predicts the sensor's x axis and another its z axis (both in
the reference frame); the predicted frame is rebuilt by Gram-Schmidt. Kyger predicted the
look direction only; this extends it to a full orientation.
"""

from __future__ import annotations

from collections import namedtuple
from collections.abc import Sequence
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.linalg import expm

from ivc import rotations
from ivc.predict.base import (
    FixedRatePredictor,
    FloatArray,
    PredictorError,
    Stream,
    TimedStepStream,
    as_given,
    check_horizons,
    check_rate,
)
from ivc.predict.timing import check_stream, check_time, repeats, restarts

KINDS = ("cp", "fogmv", "fogma", "phi2")
LOG_2PI = np.log(2.0 * np.pi)
#: Every sensor's banks (:meth:`MMAE._state`, (S, 2, ...): a bank per look vector): the filters' states ``x``
#: (S, 2, J, 3, 3) and covariances ``P``, the log probabilities ``logp`` (S, 2, J), whether started ``init``
#: (S, 2, 1) and the output weights ``w`` (S, 2, J)
State = namedtuple("State", "x P logp init w")
#: One cycle's filters: transitions ``Phi`` (J, 3, 3), process noise ``Qd`` (J, 3, 3), the measurement variance
#: ``r``, the divergence thresholds ``thr`` (J,) and the log of the probability floor ``log_pmin``
Bank = namedtuple("Bank", "Phi Qd r thr log_pmin")
#: The bank on a stream's own steps: the continuous models ``F``, ``GQG`` and ``kappa`` (``MMAE._models``)
#: Φ and Qd are made from at each step, ``r``, ``thr``, ``log_pmin`` as :data:`Bank`, the starting covariances
#: ``P0`` (J, 3, 3) and the nominal step ``tau`` s
Steps = namedtuple("Steps", "F GQG kappa r thr log_pmin P0 tau")


@dataclass(frozen=True)
class Elemental:
    """One elemental filter: ``kind``, ``sigma`` (σ; for cp the position noise density q), ``tau`` (s),
    ``threshold`` on rᵀA⁻¹r (inf = never divergent) and ``kappa`` (phi2: propagation multiple)."""

    kind: str
    sigma: float
    tau: float = 1.0
    threshold: float = np.inf
    kappa: float = 2.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise PredictorError(f"an elemental filter is one of {', '.join(KINDS)}, got {self.kind!r}")
        if not (self.sigma > 0 and self.tau > 0 and self.kappa > 0):
            raise PredictorError(f"{self.kind}: sigma, tau and kappa must be positive")

    def continuous(self) -> tuple[FloatArray, FloatArray]:
        """Per-axis F (3, 3) and white-noise spectral density matrix G Q Gᵀ (3, 3)."""
        F = np.zeros((3, 3))
        GQG = np.zeros((3, 3))
        if self.kind == "cp":
            GQG[0, 0] = self.sigma
        elif self.kind == "fogmv":
            F[0, 1], F[1, 1] = 1.0, -1.0 / self.tau
            GQG[1, 1] = 2.0 * self.sigma**2 / self.tau
        else:
            F[0, 1], F[1, 2], F[2, 2] = 1.0, 1.0, -1.0 / self.tau
            GQG[2, 2] = 2.0 * self.sigma**2 / self.tau
        return F, GQG

    def transition(self, dt: float) -> FloatArray:
        """Φ over dt as used for propagation and prediction (phi2: Φ(κ dt))."""
        F, _ = self.continuous()
        return expm(F * dt * (self.kappa if self.kind == "phi2" else 1.0))

    def discrete(self, dt: float) -> tuple[FloatArray, FloatArray]:
        """(Φ, Qd) over one step dt by Van Loan; phi2 propagates with Φ(κ dt) and Qd(dt) (docs/math.md §15.3)."""
        F, GQG = self.continuous()
        M = np.block([[-F, GQG], [np.zeros((3, 3)), F.T]]) * dt
        E = expm(M)
        Phi = E[3:, 3:].T
        Qd = Phi @ E[:3, 3:]
        return self.transition(dt), 0.5 * (Qd + Qd.T)


@numba.njit(cache=True)
def _step(z, ok, x, P, logp, init, w, bank, prow, out_pos):
    """One MMAE cycle of one look-vector bank: x (J, 3, 3) states x axes, P (J, 3, 3), logp (J,); ``bank`` a
    :data:`Bank`.

    prow (H, J, 3) are the position rows of Φ_j(δ) per horizon; out_pos (H, 3) the blended predictions;
    w (J,) receives the output weights (probabilities with divergent filters zeroed).
    """
    Phi, Qd, r, thr, log_pmin = bank
    J = x.shape[0]
    if not ok:
        out_pos[:, :] = np.nan
        return
    if init[0] == 0:
        for j in range(J):
            x[j, :, :] = 0.0
            x[j, 0, :] = z
        init[0] = 1
    d = np.empty(J)
    logf = np.empty(J)
    xm = np.empty((3, 3))
    Pm = np.empty((3, 3))
    for j in range(J):
        for a in range(3):
            for c in range(3):
                acc = 0.0
                for m in range(3):
                    acc += Phi[j, a, m] * x[j, m, c]
                xm[a, c] = acc
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for m in range(3):
                    for n in range(3):
                        acc += Phi[j, a, m] * P[j, m, n] * Phi[j, b, n]
                Pm[a, b] = acc + Qd[j, a, b]
        A = Pm[0, 0] + r
        dist = 0.0
        for c in range(3):
            res = z[c] - xm[0, c]
            dist += res * res
        d[j] = dist / A
        logf[j] = -1.5 * (LOG_2PI + np.log(A)) - 0.5 * d[j]
        for a in range(3):
            k = Pm[a, 0] / A
            for c in range(3):
                x[j, a, c] = xm[a, c] + k * (z[c] - xm[0, c])
        for a in range(3):
            for b in range(3):
                P[j, a, b] = Pm[a, b] - Pm[a, 0] * Pm[0, b] / A
    # p_j ∝ f_j p_j in the log domain, then the lower bound
    best = -np.inf
    for j in range(J):
        logp[j] += logf[j]
        best = max(best, logp[j])
    total = 0.0
    for j in range(J):
        total += np.exp(logp[j] - best)
    p = np.empty(J)
    total2 = 0.0
    for j in range(J):
        p[j] = max(np.exp(logp[j] - best) / total, np.exp(log_pmin))
        total2 += p[j]
    wsum = 0.0
    for j in range(J):
        p[j] /= total2
        w[j] = 0.0 if d[j] > thr[j] else p[j]
        wsum += w[j]
    if wsum <= 0.0:
        for j in range(J):
            w[j] = p[j]
        wsum = 1.0
    for j in range(J):
        w[j] /= wsum
    # restart divergent filters: position from the blend of the others, probability to the bound
    for j in range(J):
        if d[j] > thr[j]:
            other = 0.0
            for i in range(J):
                if i != j:
                    other += w[i]
            if other > 0.0:
                for c in range(3):
                    acc = 0.0
                    for i in range(J):
                        if i != j:
                            acc += w[i] * x[i, 0, c]
                    x[j, 0, c] = acc / other
            p[j] = np.exp(log_pmin)
    total = 0.0
    for j in range(J):
        total += p[j]
    for j in range(J):
        logp[j] = np.log(p[j] / total)
    for h in range(prow.shape[0]):
        for c in range(3):
            acc = 0.0
            for j in range(J):
                for m in range(3):
                    acc += w[j] * prow[h, j, m] * x[j, m, c]
            out_pos[h, c] = acc


@numba.njit(cache=True)
def _run(vectors, ok, state, bank, prow, out):
    """vectors (F, S, 2, 3) look vectors; out (F, S, H, 2, 3) blended predictions; ``state`` a :data:`State`,
    ``bank`` a :data:`Bank`."""
    x, P, logp, init, w = state
    for s in range(vectors.shape[1]):
        for k in range(vectors.shape[0]):
            for v in range(2):
                _step(vectors[k, s, v], ok[k, s], x[s, v], P[s, v], logp[s, v], init[s, v], w[s, v], bank, prow,
                      out[k, s, :, v])


def frame_from_axes(forward: FloatArray, up: FloatArray) -> FloatArray:
    """Quaternions (..., 4) whose x axis is along ``forward`` and z axis nearest ``up`` (Gram-Schmidt)."""
    x = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    z = up - np.sum(up * x, axis=-1, keepdims=True) * x
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return rotations.from_matrix(np.stack([x, y, z], axis=-1))


#: a working bank (docs/math.md §15.5), Kyger 1995's final tunings being lost
DEFAULT_BANK = (Elemental("cp", 0.1, threshold=8.0), Elemental("fogmv", 1.0, tau=0.115),
                Elemental("phi2", 5.0, tau=1.0))


class MMAEStepStream(TimedStepStream):
    """The live MMAE: fed time stamps, each cycle over the actual step (as the batch with times); fed none (decided
    at the first frame), the bank at the nominal step (:class:`FixedRateStream`), as the batch without times."""

    def __init__(self, predictor: MMAE, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.state = predictor._state(self.n_sensors)
        # the same arrays as the kernels take them: plain tuples (docs/kernels.md)
        self._kernel_args = tuple(self.state), tuple(predictor._steps())
        self.latest = np.zeros(self.n_sensors)

    def _step(self, qs, ok, new, gap, now):
        T = rotations.to_matrix(np.where(ok[:, None], qs, rotations.IDENTITY))
        vectors = np.ascontiguousarray(np.stack([T[:, :, 0], T[:, :, 2]], axis=1))
        state, steps = self._kernel_args
        _frame_steps(vectors, ok, new, gap, now, state, self.latest, steps)

    def _show(self, horizon):
        x, w, init = self.state.x, self.state.w, self.state.init
        pos = np.full((self.n_sensors, 2, 3), np.nan)
        now = self.clock.now if self.clock.now is not None else 0.0
        for s in np.flatnonzero(self.ok & (init[:, 0, 0] == 1)):
            _show_steps(self.predictor._models[0], self.predictor._models[2], x[s], w[s],
                        horizon + now - self.latest[s], pos[s])
        out = frame_from_axes(pos[:, 0], pos[:, 1])
        out[~self.ok] = np.nan
        return out


@dataclass
class MMAE(FixedRatePredictor):
    """Kyger's MMAE bank on the sensor's x and z axes; ``r`` the measurement variance per component."""

    rate_hz: float = 120.0
    bank: Sequence[Elemental] = DEFAULT_BANK
    r: float = 1e-4
    p_min: float = 1e-2
    p0_velocity: float = 1.0
    p0_acceleration: float = 10.0
    name: str = "mmae"
    _config: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        if not self.bank:
            raise PredictorError("an MMAE needs at least one elemental filter")
        if not (self.r > 0 and 0 < self.p_min < 1.0 / len(self.bank)):
            raise PredictorError(f"need r > 0 and 0 < p_min < 1/{len(self.bank)}")
        Phi, Qd = zip(*(e.discrete(self.tau) for e in self.bank), strict=True)
        P0 = np.zeros((len(self.bank), 3, 3))
        for j, e in enumerate(self.bank):
            P0[j, 0, 0] = self.r
            if e.kind != "cp":
                P0[j, 1, 1] = self.p0_velocity
            if e.kind in ("fogma", "phi2"):
                P0[j, 2, 2] = self.p0_acceleration
        thr = np.array([e.threshold for e in self.bank], float)
        self._config = (np.array(Phi), np.array(Qd), P0, thr)
        F, GQG = zip(*(e.continuous() for e in self.bank), strict=True)
        kappa = np.array([e.kappa if e.kind == "phi2" else 1.0 for e in self.bank])
        self._models = (np.array(F), np.array(GQG), kappa)

    def position_rows(self, horizons: FloatArray) -> FloatArray:
        """Position rows of Φ_j(δ) (H, J, 3): the prediction operator of each elemental filter."""
        return np.array([[e.transition(d)[0] for e in self.bank] for d in horizons])

    def _steps(self) -> Steps:
        """The :data:`Steps` of the bank."""
        return Steps(*self._models, self.r, self._config[3], np.log(self.p_min), self._config[2], self.tau)


    def _state(self, S: int) -> State:
        J = len(self.bank)
        P = np.broadcast_to(self._config[2], (S, 2, J, 3, 3)).copy()
        return State(np.zeros((S, 2, J, 3, 3)), P, np.full((S, 2, J), -np.log(J)), np.zeros((S, 2, 1), np.int64),
                np.full((S, 2, J), 1.0 / J))

    def _predict_uniform(self, q, horizons, valid=None):
        h = check_horizons(horizons)
        qs, ok, single = check_stream(q, valid)
        F, S = ok.shape
        T = rotations.to_matrix(np.where(ok[..., None], qs, rotations.IDENTITY))
        vectors = np.ascontiguousarray(np.stack([T[..., :, 0], T[..., :, 2]], axis=2))
        Phi, Qd, _, thr = self._config
        out = np.zeros((F, S, len(h), 2, 3))
        _run(vectors, ok, tuple(self._state(S)), tuple(Bank(Phi, Qd, self.r, thr, np.log(self.p_min))),
             self.position_rows(h), out)
        pred = frame_from_axes(out[..., 0, :], out[..., 1, :])
        pred[~ok] = np.nan
        pred = np.moveaxis(pred, 2, 0)
        return as_given(pred, single)

    def _stream_uniform(self, n_sensors: int = 1) -> MMAEStream:
        return MMAEStream(self, n_sensors)

    def predict(self, q, horizons, valid=None, time=None):
        """Without ``time``, the bank at the nominal step; with it, each cycle over the actual step (Φ and Qd by
        Van Loan at that step), repeats dropped and predicted from the sample they repeat, gaps restarting it."""
        if time is None:
            return super().predict(q, horizons, valid)
        h = check_horizons(horizons)
        qs, ok, single = check_stream(q, valid)
        F, S = ok.shape
        t = check_time(time, F, self.rate_hz)
        use = ok & ~repeats(qs, ok)
        T = rotations.to_matrix(np.where(ok[..., None], qs, rotations.IDENTITY))
        vectors = np.ascontiguousarray(np.stack([T[..., :, 0], T[..., :, 2]], axis=2))
        out = np.zeros((F, S, len(h), 2, 3))
        _run_steps(vectors, ok, use, restarts(t, ok, self.max_gap_s), t, h, tuple(self._state(S)), np.zeros(S),
                   tuple(self._steps()), out)
        pred = frame_from_axes(out[..., 0, :], out[..., 1, :])
        pred[~ok] = np.nan
        return as_given(np.moveaxis(pred, 2, 0), single)

    #: the live form, made by :meth:`stream`
    stream_type = MMAEStepStream


class MMAEStream(Stream):
    def __init__(self, predictor: MMAE, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.state = predictor._state(self.n_sensors)
        Phi, Qd, _, thr = predictor._config
        # the same arrays as the kernels take them: plain tuples (docs/kernels.md)
        self._kernel_args = tuple(self.state), tuple(Bank(Phi, Qd, predictor.r, thr, np.log(predictor.p_min)))
        self.ok = np.zeros(self.n_sensors, bool)
        self._rows: dict[float, FloatArray] = {}
        self._now = predictor.position_rows(np.zeros(1))  # the kernel's own (unused) output horizon

    def update(self, q, valid=None):
        qs, ok = self._check_frame(q, valid)
        T = rotations.to_matrix(np.where(ok[:, None], qs, rotations.IDENTITY))
        vectors = np.ascontiguousarray(np.stack([T[:, :, 0], T[:, :, 2]], axis=1))[None]
        out = np.zeros((1, self.n_sensors, 1, 2, 3))
        _run(vectors, ok[None], *self._kernel_args, self._now, out)
        self.ok = ok

    def predict(self, horizon):
        d = float(check_horizons(horizon)[0])
        if d not in self._rows:
            self._rows[d] = self.predictor.position_rows(np.array([d]))[0]
        x = self.state.x  # (S, 2, J, 3 states, 3 axes)
        w = self.state.w
        pos = np.einsum("svj,jm,svjmc->svc", w, self._rows[d], x)
        out = frame_from_axes(pos[:, 0], pos[:, 1])
        out[~self.ok] = np.nan
        return out


# ---- on a stream's own time steps ---------------------------------------------------------------------------


@numba.njit(cache=True)
def _expm(A):
    """expm(A) of a small matrix by scaling and squaring of its Taylor series (18 terms after scaling to ‖A‖ <= 1/2)."""
    n = A.shape[0]
    norm = 0.0
    for i in range(n):
        row = 0.0
        for j in range(n):
            row += abs(A[i, j])
        norm = max(norm, row)
    s = 0
    while norm > 0.5:
        norm /= 2.0
        s += 1
    B = A / 2.0**s
    E = np.eye(n)
    term = np.eye(n)
    for k in range(1, 19):
        term = term @ B / k
        E += term
    for _ in range(s):
        E = E @ E
    return E


@numba.njit(cache=True)
def _discrete(F, GQG, kappa, dt, Phi, Qd):
    """Phi (J, 3, 3), Qd (J, 3, 3) over dt: Van Loan, as :meth:`Elemental.discrete` (phi2: Φ(κ dt), Qd(dt))."""
    J = F.shape[0]
    M = np.zeros((6, 6))
    for j in range(J):
        for a in range(3):
            for b in range(3):
                M[a, b] = -F[j, a, b] * dt
                M[a, 3 + b] = GQG[j, a, b] * dt
                M[3 + a, 3 + b] = F[j, b, a] * dt
                M[3 + a, b] = 0.0
        E = _expm(M)
        Ph = np.ascontiguousarray(E[3:, 3:].T)
        Q = Ph @ np.ascontiguousarray(E[:3, 3:])
        Phi[j] = _expm(F[j] * (dt * kappa[j]))
        for a in range(3):
            for b in range(3):
                Qd[j, a, b] = 0.5 * (Q[a, b] + Q[b, a])


@numba.njit(cache=True)
def _show_steps(F, kappa, x, w, horizon, out):
    """out (2, 3) = Σ_j w_j [Φ_j(horizon) x̂_j]_position for both look vectors (x (2, J, 3, 3), w (2, J))."""
    J = F.shape[0]
    for j in range(J):
        row = _expm(F[j] * (horizon * kappa[j]))[0]
        for v in range(2):
            for c in range(3):
                if j == 0:
                    out[v, c] = 0.0
                acc = 0.0
                for m in range(3):
                    acc += row[m] * x[v, j, m, c]
                out[v, c] += w[v, j] * acc


@numba.njit(cache=True)
def _frame_steps(vectors, ok, use, restart, now, state, last, steps):
    """One frame for every sensor on its actual step: vectors (S, 2, 3); last (S,) each one's latest usable time;
    ``state`` a :data:`State`, ``steps`` a :data:`Steps`."""
    x, P, logp, init, w = state
    F, GQG, kappa, r, thr, log_pmin, P0, tau = steps
    S, J = vectors.shape[0], F.shape[0]
    Phi = np.empty((J, 3, 3))
    Qd = np.empty((J, 3, 3))
    none = np.zeros((0, J, 3))
    dummy = np.empty((0, 2, 3))[:, 0]  # strided like the batch's out[k, s, :, v]: one specialisation of _step
    for s in range(S):
        if not ok[s]:
            continue
        if restart[s]:
            for v in range(2):
                init[s, v, 0] = 0
                for j in range(J):
                    P[s, v, j] = P0[j]
                    logp[s, v, j] = -np.log(J)
                    w[s, v, j] = 1.0 / J
        if not use[s]:
            continue
        dt = now - last[s] if init[s, 0, 0] == 1 else tau
        _discrete(F, GQG, kappa, dt, Phi, Qd)
        for v in range(2):
            _step(vectors[s, v], np.bool_(True), x[s, v], P[s, v], logp[s, v], init[s, v], w[s, v],
                  (Phi, Qd, r, thr, log_pmin), none, dummy)  # a Bank, as _run's: a plain tuple
        last[s] = now


@numba.njit(cache=True)
def _run_steps(vectors, ok, use, restart, t, horizons, state, last, steps, out):
    """The batch on the stream's steps: out (F, S, H, 2, 3) the blended look vectors, from each frame's latest usable
    sample (horizon + its age); ``state`` a :data:`State`, ``steps`` a :data:`Steps`."""
    x, P, logp, init, w = state
    F, GQG, kappa, r, thr, log_pmin, P0, tau = steps
    for k in range(vectors.shape[0]):
        _frame_steps(vectors[k], ok[k], use[k], restart[k], t[k], state, last, steps)
        for s in range(vectors.shape[1]):
            if ok[k, s] and init[s, 0, 0] == 1:
                for i in range(horizons.shape[0]):
                    _show_steps(F, kappa, x[s], w[s], horizons[i] + t[k] - last[s], out[k, s, i])
            else:
                out[k, s, :, :, :] = np.nan
