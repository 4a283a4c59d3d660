"""``auto``, the default predictor: a bank of simple and thesis filters, each sensor shown the one that has
lately predicted its own stream best.

No fixed set of noise values suits every stream: the thesis's filters are tuned to its 120 Hz
electromagnetic tracker and to aggressive head motion, while a headset's fused poses at 60 Hz are
smoother and a static sensor's are noise only. ``auto`` runs every filter of :data:`CANDIDATES` on the
stream and scores each, causally, against the stream's own later samples: the prediction made at
frame k for t(k) + h is compared, once the sample after t(k) + h has arrived, with the orientation
slerped there (the rule of :mod:`ivc.predict.recording`; references between samples more than
40 ms apart are not scored). Each candidate's geodesic errors are summed with an exponential
forgetting of time constant ``memory_s`` (1 s), and each frame shows the candidates' turns from the
measured orientation averaged with weights (smallest sum / the candidate's sum)^``power`` (8),
normalised: in effect the best candidate, blended with the nearly as good ones (while nothing is
scored, ``none``; a sum of exactly 0 takes all the weight, ties to the earlier candidate). Where a
candidate has no prediction yet, its turn is 0 (the measured orientation). In batch the weights are
kept per horizon; the live form scores at ``horizon_s`` and uses those weights at any horizon.

One more member, ``combine`` (on unless ``combination=False``), is not a filter of its own: the
candidates' turns combined with weights learned online by constrained least squares from the targets
whose time has arrived (:mod:`ivc.predict.combine`); it is scored and blended like the others.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numba
import numpy as np

from ivc import rotations
from ivc.predict.base import (
    FloatArray,
    Predictor,
    PredictorError,
    Stream,
    StreamClock,
    as_given,
    check_horizons,
    check_rate,
)
from ivc.predict.combine import MEMORY_S as COMBINATION_MEMORY_S
from ivc.predict.combine import accumulate, combine, decay, ridge_for, solve_weights
from ivc.predict.direct import DirectPredictor
from ivc.predict.dq import SIGMA_CV1, dqekf_ca, dqekf_cv, mmdq2
from ivc.predict.hold import NoPrediction
from ivc.predict.linear import polynomial
from ivc.predict.quat import delta_q, qmul, qmul_conj, rate_of, slerp
from ivc.predict.recording import REFERENCE_MAX_STEP_S, future_reference
from ivc.predict.timing import check_stream, check_time, repeats


def _cv_brisk(rate_hz: float) -> Predictor:
    """DQ-EKF CV with 3x Table 10's process noise: the bandwidth of a smoother, less noisy tracker."""
    p = dqekf_cv(rate_hz, sigma_w=lambda kind, lam: tuple(3.0 * np.asarray(SIGMA_CV1)))
    p.name = "dqekf-cv-x3"
    return p


#: the bank: name -> factory(rate_hz). Order matters only for ties (the first wins) and the start (the first).
CANDIDATES = {
    "none": NoPrediction,
    "poly1": lambda rate_hz: polynomial(rate_hz, 1),
    "dqekf-cv": dqekf_cv,
    "dqekf-cv-x3": _cv_brisk,
    "dqekf-ca": dqekf_ca,
    "mmdq2": mmdq2,
    "direct": DirectPredictor,
    # the same learner with twice the history and with ten times the memory: members that differ where it matters
    "direct-8": lambda rate_hz: DirectPredictor(rate_hz, lags=8, name="direct-8"),
    "direct-30s": lambda rate_hz: DirectPredictor(rate_hz, memory_s=30.0, name="direct-30s"),
}
#: time constant (s) of the forgetting of past errors
MEMORY_S = 1.0
#: a candidate's weight is (smallest error sum / its error sum) to this power, normalised
POWER = 8.0


#: error sums within this relative difference are a tie, won by the earlier candidate: candidates that make the
#: same prediction (a DQ filter's first rate is the backward difference) must not be told apart by rounding
TIE = 1e-9


@numba.njit(cache=True)
def _first_best(total):
    """The first index whose value is within TIE (relative) of the smallest."""
    low = total[0]
    for c in range(1, total.shape[0]):
        low = min(low, total[c])
    for c in range(total.shape[0]):
        if total[c] <= low + TIE * abs(low):
            return c
    return 0


@numba.njit(cache=True)
def _weights(total, power, out):
    """out (C,) = (smallest sum / each sum)^power, normalised; all on the first best while the smallest is 0."""
    low = total[0]
    for c in range(1, total.shape[0]):
        low = min(low, total[c])
    if not low > 0.0:
        out[:] = 0.0
        out[_first_best(total)] = 1.0
        return
    acc = 0.0
    for c in range(total.shape[0]):
        out[c] = (low / total[c]) ** power
        acc += out[c]
    for c in range(total.shape[0]):
        out[c] /= acc


@numba.njit(cache=True)
def _weigh(total, power, out):
    """out[s] = :func:`_weights` of each sensor's row of total (S, C)."""
    for s in range(total.shape[0]):
        _weights(total[s], power, out[s])


@numba.njit(cache=True)
def _select(err, known, dt, memory, power, out):
    """out[k] (C,) = the candidates' weights at frame k from their forgotten error sums (err (C, F) mrad, NaN =
    unscored; known (F,) the frame each error is first known at, −1 never; dt (F,) s between frames)."""
    C, F = err.shape
    order = np.argsort(known, kind="mergesort")
    total = np.zeros(C)
    e = 0
    while e < F and known[order[e]] < 0:
        e += 1
    for j in range(F):
        if dt[j] > 0.0:
            decay = np.exp(-dt[j] / memory)
            for c in range(C):
                total[c] *= decay
        while e < F and known[order[e]] == j:
            k = order[e]
            if np.isfinite(err[0, k]):
                for c in range(C):
                    total[c] += err[c, k]
            e += 1
        _weights(total, power, out[j])


@numba.njit(cache=True)
def _score(shown, base, sensors, q, knot_q, knot_t, now, target, max_step, total, members, sums):
    """Add the errors (mrad) of one frame's pending predictions shown (S, C, 4) for ``target`` s to total (S, C),
    for the sensors whose sample q (S, 4) at ``now`` just arrived: the reference is slerped between each one's
    previous usable sample (knot_q, knot_t) and q, as :func:`ivc.predict.recording.future_reference` does.
    With ``members`` > 0, the first ``members`` predictions' turns from the frame's measured orientation base
    (S, 4), in its body frame, and the reference's are added to the combination's ``sums``, (A (S, 3, m, m),
    b (S, 3, m))."""
    A, b = sums
    S, C = total.shape
    ref = np.empty(4)
    d = np.empty(4)
    turns = np.empty((max(members, 1), 3))
    goal = np.empty(3)
    for s in range(S):
        if not sensors[s]:
            continue
        if target == now:
            for i in range(4):
                ref[i] = q[s, i]
        elif np.isfinite(knot_t[s]) and target >= knot_t[s] and now - knot_t[s] <= max_step:
            u = (target - knot_t[s]) / (now - knot_t[s])
            slerp(knot_q[s], q[s], u, ref)
        else:
            continue
        for c in range(C):
            qmul_conj(shown[s, c], ref, d)
            v = np.sqrt(d[1] ** 2 + d[2] ** 2 + d[3] ** 2)
            total[s, c] += 1e3 * 2.0 * np.arctan2(v, abs(d[0]))
        if members > 0:
            for c in range(members):
                _body_turn(base[s], shown[s, c], d, turns[c])
            _body_turn(base[s], ref, d, goal)
            accumulate(turns, goal, A[s], b[s])


@numba.njit(cache=True)
def _body_turn(q, p, d, out):
    """out (3,) = the rotation vector of q* ⊗ p (the turn from q to p in q's frame; scalar part made non-negative),
    rad; d a (4,) scratch."""
    qc = np.empty(4)
    qc[0] = q[0]
    for i in range(1, 4):
        qc[i] = -q[i]
    qmul(qc, p, d)
    if d[0] < 0.0:
        for i in range(4):
            d[i] = -d[i]
    rate_of(d, 1.0, out)


@numba.njit(cache=True)
def _solve_all(A, b, ridge, out):
    """out[s] (3, m) = :func:`ivc.predict.combine.solve_weights` of each sensor's sums A (S, 3, m, m), b (S, 3, m)."""
    for s in range(A.shape[0]):
        solve_weights(A[s], b[s], ridge, out[s])


@numba.njit(cache=True)
def _combine_frame(ahead, weights, last, ok, out):
    """out (S, 4) = last ⊗ exp(Σ_c w_ac r_ac) per sensor: r_c the body-frame turn from last (S, 4) to ahead (C, S, 4),
    weights (S, 3, C); the measured orientation where not ok."""
    C, S = ahead.shape[0], ahead.shape[1]
    d = np.empty(4)
    r = np.empty(3)
    m = np.empty(3)
    dq = np.empty(4)
    for s in range(S):
        if not ok[s]:
            out[s, :] = last[s]
            continue
        m[:] = 0.0
        for c in range(C):
            _body_turn(last[s], ahead[c, s], d, r)
            for a in range(3):
                m[a] += weights[s, a, c] * r[a]
        delta_q(m[0], m[1], m[2], 1.0, dq)
        qmul(last[s], dq, out[s])


@numba.njit(cache=True)
def _blend_frame(ahead, weights, last, ok, out):
    """out (S, 4) = :func:`blend` of one frame: ahead (C, S, 4), weights (S, C), last (S, 4); NaN where not ok."""
    C, S = ahead.shape[0], ahead.shape[1]
    d = np.empty(4)
    v = np.empty(3)
    dq = np.empty(4)
    for s in range(S):
        if not ok[s]:
            out[s, :] = np.nan
            continue
        mx = my = mz = 0.0
        for c in range(C):
            qmul_conj(ahead[c, s], last[s], d)
            if d[0] < 0.0:
                for i in range(4):
                    d[i] = -d[i]
            rate_of(d, 1.0, v)
            mx += weights[s, c] * v[0]
            my += weights[s, c] * v[1]
            mz += weights[s, c] * v[2]
        delta_q(mx, my, mz, 1.0, dq)
        qmul(dq, last[s], out[s])


def blend(shown: FloatArray, weights: FloatArray, q: FloatArray) -> FloatArray:
    """exp(Σ_c w_c log(shown_c ⊗ q*)) ⊗ q: the candidates' turns from the measured q (..., 4), weighted (C, ...)."""
    turn = rotations.to_rotvec(rotations.multiply(shown, rotations.conjugate(q)))
    mean = np.einsum("c...,c...k->...k", weights, turn)
    return rotations.multiply(rotations.from_rotvec(mean), np.broadcast_to(q, shown.shape[1:]))


class AutoStream(Stream):
    """The live ``auto``: every candidate's stream, the pending predictions of each sensor, the error sums."""

    def __init__(self, predictor: AutoPredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.streams = [p.stream(n_sensors) for p in predictor.bank]
        self.clock = StreamClock(predictor.rate_hz, n_sensors)
        C = len(self.streams)
        self.combined = C if predictor.combination else 0  # how many candidates the combination learns from (0: off)
        M = len(predictor.members)
        self.total = np.zeros((n_sensors, M))
        self.weights = np.zeros((n_sensors, M))
        self.weights[:, 0] = 1.0
        self.A = np.zeros((n_sensors, 3, C, C))  # the combination's sums and weights, per axis
        self.b = np.zeros((n_sensors, 3, C))
        self.mix = np.full((n_sensors, 3, C), 1.0 / C)
        self.ridge = ridge_for(predictor.horizon_s)
        # scoring at 0 s leaves the combination nothing to learn: it keeps equal weights
        self.learning = self.combined if predictor.horizon_s > 0 else 0
        # (target time, shown (S, M, 4), the measured orientation (S, 4), the sensors still to score (S,)), by time
        self.pending = deque()
        self.previous = np.full((n_sensors, 4), np.nan)  # the latest valid sample (repeat test)
        self.knot_t = np.full(n_sensors, np.nan)  # the latest usable sample: time, orientation
        self.knot_q = np.full((n_sensors, 4), np.nan)
        self.ok = np.zeros(n_sensors, bool)
        self.ahead = None  # the candidates' predictions (C, S, 4) at horizon_s from the latest frame

    @property
    def restarts(self) -> int:
        return max(s.restarts for s in self.streams)

    def update(self, q, valid=None, time=None):
        qs, ok = self._check_frame(q, valid)
        for s in self.streams:
            s.update(qs, ok, time)
        dt = self.clock.tick(time)
        now = self.clock.now
        p = self.predictor
        if dt > 0:
            self.total *= np.exp(-dt / p.memory_s)
            if self.learning:
                # flattened over the sensors, as combine's batch passes them (3, C, C) and (3, C): one specialisation
                C = self.A.shape[-1]
                decay(self.A.reshape(-1, C, C), self.b.reshape(-1, C), np.exp(-dt / p.combination_memory_s))
        usable = ok & ~np.all(qs == self.previous, axis=1)
        self.previous = np.where(ok[:, None], qs, self.previous)
        if np.any(usable):
            for target, shown, base, waiting in self.pending:  # each scored at the sensor's first usable sample after
                if target > now:
                    break
                _score(shown, base, waiting & usable, qs, self.knot_q, self.knot_t, now, target, p.max_step_s,
                       self.total, self.learning, (self.A, self.b))
                waiting &= ~usable
            while self.pending and self.pending[0][0] <= now and not self.pending[0][3].any():
                self.pending.popleft()
        self.knot_t = np.where(usable, now, self.knot_t)
        self.knot_q = np.where(usable[:, None], qs, self.knot_q)
        _weigh(self.total, p.power, self.weights)
        if self.learning:
            _solve_all(self.A, self.b, self.ridge, self.mix)
        self.ok = ok
        self.last = qs
        self.ahead = None
        if np.any(ok):
            self.ahead = self._ahead(p.horizon_s)
            self.pending.append((now + p.horizon_s, np.ascontiguousarray(self.ahead.transpose(1, 0, 2)), qs, ok.copy()))

    def _ahead(self, horizon: float) -> FloatArray:
        """Every member's prediction (M, S, 4) at ``horizon`` s from the latest frame; the measured orientation
        where a candidate has none, as in batch."""
        C = len(self.streams)
        out = np.empty((C + (1 if self.combined else 0), self.n_sensors, 4))
        for c, s in enumerate(self.streams):
            out[c] = s.predict(horizon)
        ahead = out[:C]
        ahead[:] = np.where(np.all(np.isfinite(ahead), axis=-1, keepdims=True), ahead, self.last[None])
        if self.combined:
            if horizon > 0.0:
                _combine_frame(ahead, self.mix, self.last, self.ok, out[C])
            else:
                out[C] = self.last
        return out

    def predict(self, horizon):
        d = float(check_horizons(horizon)[0])
        if self.ahead is not None and d == self.predictor.horizon_s:  # the live loop's case: computed by update
            ahead = self.ahead
        else:
            ahead = self._ahead(d)
        out = np.empty((self.n_sensors, 4))
        _blend_frame(ahead, self.weights, self.last, self.ok, out)
        return out


@dataclass
class AutoPredictor(Predictor):
    """The bank of :data:`CANDIDATES`, each sensor and horizon shown its best recent candidate (module docstring)."""

    rate_hz: float = 120.0
    candidates: tuple[str, ...] = tuple(CANDIDATES)
    memory_s: float = MEMORY_S
    power: float = POWER
    horizon_s: float = 0.05  # the live form's scoring horizon
    max_step_s: float = REFERENCE_MAX_STEP_S
    combination: bool = True  # the ``combine`` member (module docstring)
    combination_memory_s: float = COMBINATION_MEMORY_S
    name: str = "auto"
    bank: list = field(init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        unknown = [c for c in self.candidates if c not in CANDIDATES]
        if unknown or not self.candidates:
            raise PredictorError(f"auto's candidates are among {', '.join(CANDIDATES)}; got {self.candidates}")
        if not (self.memory_s > 0 and self.max_step_s > 0 and self.power >= 0 and self.combination_memory_s > 0):
            raise PredictorError("memory_s, combination_memory_s and max_step_s must be positive numbers of seconds, "
                                 "power >= 0")
        check_horizons(self.horizon_s)
        self.bank = [CANDIDATES[c](self.rate_hz) for c in self.candidates]
        for p in self.bank:  # a member that learns from its errors (direct) learns at the horizon auto scores at
            if hasattr(p, "horizon_s") and self.horizon_s > 0:
                p.horizon_s = float(self.horizon_s)

    @property
    def members(self) -> tuple[str, ...]:
        """The names of what is blended, in the order of the weights: the candidates, then ``combine`` if on."""
        return tuple(self.candidates) + (("combine",) if self.combination else ())

    def _combined(self, shown, qs, ok, t, horizon, references) -> FloatArray:
        """The ``combine`` member (F, S, 4) at one horizon from the candidates' predictions shown (C, F, S, 4)."""
        out = np.array(qs)
        if horizon == 0.0:  # nothing to learn: the measurement
            return out
        turns = rotations.to_rotvec(rotations.multiply(rotations.conjugate(qs)[None], shown))  # (C, F, S, 3), body
        turns[:, ~ok] = 0.0
        for s, (ref, scored, known) in enumerate(references):
            goal = np.full((len(t), 3), np.nan)
            goal[scored] = rotations.to_rotvec(rotations.multiply(rotations.conjugate(qs[scored, s]), ref[scored]))
            mean, _ = combine(turns[:, :, s], goal, known, t, horizon, self.combination_memory_s)
            out[ok[:, s], s] = rotations.multiply(qs[ok[:, s], s], rotations.from_rotvec(mean[ok[:, s]]))
        return out

    def selections(self, q, horizons, valid=None, time=None) -> tuple[FloatArray, np.ndarray]:
        """(predictions (H, F, S, 4) as :meth:`predict`, the members' weights (H, F, S, M), in :attr:`members`'
        order)."""
        h = check_horizons(horizons)
        qs, ok, _ = check_stream(q, valid)
        F, S = ok.shape
        t = check_time(time, F, self.rate_hz)
        dt = np.diff(t, prepend=t[:1])
        usable = ok & ~repeats(qs, ok)
        shown = []
        for p in self.bank:
            P = p.predict(qs, h, ok, time=t)
            shown.append(np.where(np.all(np.isfinite(P), axis=-1, keepdims=True), P, qs[None]))
        shown = np.stack(shown)  # (C, H, F, S, 4)
        references = []  # per horizon, per sensor: (reference, scored, the frame it is known at or -1)
        for d in h:
            references.append([])
            for s in range(S):
                ref, inside, known = future_reference(t, qs[:, s], usable[:, s], d, self.max_step_s, known_at=True)
                scored = inside & ok[:, s]
                references[-1].append((ref, scored, np.where(scored, known, -1)))
        if self.combination:
            mixed = [self._combined(shown[:, i], qs, ok, t, float(d), references[i]) for i, d in enumerate(h)]
            shown = np.concatenate([shown, np.stack(mixed)[None]])
        M = shown.shape[0]
        weights = np.zeros((len(h), F, S, M))
        for i in range(len(h)):
            for s, (ref, scored, known) in enumerate(references[i]):
                err = np.full((M, F), np.nan)
                err[:, scored] = 1e3 * rotations.angle_between(shown[:, i, scored, s], ref[scored][None])
                chosen = np.empty((F, M))  # contiguous, whatever S: one specialisation of _select
                _select(err, known, dt, self.memory_s, self.power, chosen)
                weights[i, :, s] = chosen
        out = blend(shown, np.moveaxis(weights, -1, 0), qs[None])
        out[:, ~ok] = np.nan
        return out, weights

    def predict(self, q, horizons, valid=None, time=None):
        out, _ = self.selections(q, horizons, valid, time)
        return as_given(out, np.ndim(q) == 2)

    #: the live form, made by :meth:`stream`
    stream_type = AutoStream
