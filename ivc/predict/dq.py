"""Delta-quaternion predictors of Himberg 2010: DQ-EKF CV and CA, and the multiple-model MMDQ2 / MMDQ3.

Each estimates the angular velocity ω (and for CA models the angular acceleration α) from
the delta quaternions of the measured stream, then extrapolates the *measured* orientation
(docs/math.md §11.4, §12.2-§12.6; corrected equations, tuning from Table 10 and eq. 67).

Switches for the thesis's variants (docs/math.md §12.3-§12.6), with the defaults used here:

* ``h_jacobian``: H of a CA model, ``"standard"`` [J, 0] (the EKF's ∂h/∂x at x⁻),
  ``"thesis"`` [J, τJ] (eq. 59-60), or ``"midpoint"`` (Δq measures ω − ατ/2).
* ``mode_weights``: ``"imm"`` (c̄_j L_j, standard IMM) or ``"thesis"`` (μ_j(k−1) L_j, L758).
* ``adaptive_tpm``: the quasi-Bayesian transition-matrix update (eq. 45-47, row-i form), on by default.
* ``mmdq3_models`` (MMDQ3 only): ``"cv-ca-ca"`` (Table 10) or ``"cv-cv-ca"`` (the text's other reading).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from ivc.predict import dq_kernels as K
from ivc.predict.base import (
    MAX_HORIZON,
    FloatArray,
    Predictor,
    PredictorError,
    Stream,
    as_given,
    check_horizons,
    check_rate,
)
from ivc.predict.delta import extrapolate_each
from ivc.predict.timing import MAX_GAP_S, check_stream, check_time, steps

#: Table 10 process-noise standard deviations: CV in rad/s², CA in rad/s³
SIGMA_CV1 = (1.48, 0.63, 0.72)
SIGMA_CV2 = (2.96, 1.26, 1.44)  # docs/math.md §12.6: CV at λ = 1.0, 2 x CV1 (derived; not in Himberg 2010)
SIGMA_CA = (176.0, 76.0, 86.0)
SIGMA_CA1 = (353.0, 152.0, 175.0)
SIGMA_CA2 = (708.0, 304.0, 350.0)
#: Table 10 by (model kind, manoeuvring index λ it was tuned at, docs/math.md §13.3)
TABLE_10 = {("cv", 0.5): SIGMA_CV1, ("cv", 1.0): SIGMA_CV2, ("ca", 0.5): SIGMA_CA, ("ca", 1.0): SIGMA_CA1,
            ("ca", 2.0): SIGMA_CA2}
#: eq. 67 measurement noise of Δq: standard deviations of its 4 components
SIGMA_DQ = (2.09e-06, 2.2e-04, 8.22e-05, 7.92e-05)
#: initial transition matrices (rows = from, columns = to), eq. 66 and 65
PI_MMDQ2 = ((0.971, 0.029), (0.065, 0.935))
PI_MMDQ3 = ((0.970, 0.029, 0.001), (0.069, 0.917, 0.014), (0.001, 0.250, 0.749))
H_JACOBIANS = {"standard": 0.0, "thesis": 1.0, "midpoint": 2.0}
MODE_WEIGHTS = {"imm": 0.0, "thesis": 1.0}
#: floors on mixing and mode probabilities (the thesis gives no values; ivc uses 1e-4, docs/math.md §12.4)
EPS = 1e-4


@dataclass(frozen=True)
class Model:
    """One elemental DQ-EKF: ``kind`` "cv" or "ca" and its process-noise standard deviations per axis."""

    kind: str
    sigma_w: tuple[float, float, float]

    def __post_init__(self):
        if self.kind not in ("cv", "ca"):
            raise PredictorError(f"a DQ model is 'cv' or 'ca', got {self.kind!r}")
        if len(self.sigma_w) != 3 or not all(np.isfinite(s) and s > 0 for s in self.sigma_w):
            raise PredictorError(f"sigma_w must be 3 positive numbers, got {self.sigma_w}")


def stationary(Pi: ArrayLike) -> FloatArray:
    """Stationary distribution of a row-stochastic matrix."""
    Pi = np.asarray(Pi, dtype=float)
    w, v = np.linalg.eig(Pi.T)
    p = np.real(v[:, np.argmin(np.abs(w - 1.0))])
    return p / p.sum()


class DQStream(Stream):
    """Streaming DQ predictor: one compiled step per sensor per frame."""

    def __init__(self, predictor: DQPredictor, n_sensors: int):
        super().__init__(predictor, n_sensors)
        self.state = predictor._state(self.n_sensors)
        self._states = tuple(self.state)  # the same arrays, as the kernels take them (dq_kernels)
        self._model = tuple(K.Model(*predictor._config[:4]))
        self.ready = np.zeros(self.n_sensors, bool)
        self._all = np.ones(self.n_sensors, bool)
        self.now: float | None = None  # the last frame's time (s), when frames come with time stamps
        self._step = 0.0  # dt of the next frame fed without a time stamp (0 for the first)

    def update(self, q, valid=None, time=None):
        q = np.array(q, dtype=float, order="C")  # a copy: normalised in place by the kernel
        if q.shape != (self.n_sensors, 4):
            raise PredictorError(f"a frame has shape ({self.n_sensors}, 4), got {q.shape}")
        ok = self._all if valid is None else np.asarray(valid, dtype=bool).reshape(self.n_sensors)
        if time is None:  # the live path's default: one nominal period, no clock kept
            dt = self._step
            self._step = self.predictor.tau
        else:
            t = float(time)
            if self.now is not None and not t > self.now:
                raise PredictorError(f"frame time {t!r} s does not come after the previous frame's ({self.now!r} s): "
                                     "feed frames in time order, without repeated time stamps")
            dt = 0.0 if self.now is None else t - self.now
            self.now = t
            self._step = self.predictor.tau
        bad = K.update_frame(q, ok, dt, self._states, self._model, self.ready)
        if bad >= 0:
            raise PredictorError(f"sensor {bad}: not a unit quaternion (norm {np.linalg.norm(q[bad]):.6g}); "
                                 "pass unit quaternions [w, x, y, z]")
        self.last = q

    def predict(self, horizon):
        d = float(horizon)
        if not 0.0 <= d <= MAX_HORIZON:
            check_horizons(horizon)
        out = np.empty((self.n_sensors, 4))
        K.predict_frame(self.last, self.state.est, self.state.clock, self.ready, d, self.predictor.tau, out)
        return out

    @property
    def restarts(self) -> int:
        """Restarts at gaps so far, summed over the sensors."""
        return int(self.state.clock[:, K.CLOCK_RESTARTS].sum())

    @property
    def omega(self) -> FloatArray:
        """Current angular-velocity estimates (sensors, 3) rad/s."""
        return self.state.est[:, :3].copy()


@dataclass
class DQPredictor(Predictor):
    """An IMM over DQ-EKF models (one model = a plain DQ-EKF). See the module docstring for the switches."""

    models: Sequence[Model]
    rate_hz: float = 120.0
    transition: ArrayLike | None = None
    sigma_v: Sequence[float] = SIGMA_DQ
    h_jacobian: str = "standard"
    mode_weights: str = "imm"
    adaptive_tpm: bool = True
    eps_mix: float = EPS
    eps_mu: float = EPS
    p0_omega: float = 1.0
    p0_alpha: float = 100.0
    max_gap_s: float = MAX_GAP_S
    name: str = "dq"
    _config: tuple = field(init=False, repr=False)

    def __post_init__(self):
        self.rate_hz = check_rate(self.rate_hz)
        if not self.models:
            raise PredictorError("a DQ predictor needs at least one model")
        if self.h_jacobian not in H_JACOBIANS:
            raise PredictorError(f"h_jacobian is one of {sorted(H_JACOBIANS)}, got {self.h_jacobian!r}")
        if self.mode_weights not in MODE_WEIGHTS:
            raise PredictorError(f"mode_weights is one of {sorted(MODE_WEIGHTS)}, got {self.mode_weights!r}")
        M = len(self.models)
        Pi = np.eye(1) if M == 1 and self.transition is None else np.asarray(self.transition, dtype=float)
        if Pi.shape != (M, M) or np.any(Pi < 0) or not np.allclose(Pi.sum(axis=1), 1.0, atol=1e-6):
            raise PredictorError(f"the transition matrix must be {M}x{M}, non-negative, rows summing to 1")
        Pi = Pi / Pi.sum(axis=1, keepdims=True)
        sigma_v = np.asarray(self.sigma_v, dtype=float)
        if sigma_v.shape != (4,) or np.any(sigma_v <= 0):
            raise PredictorError(f"sigma_v must be 4 positive standard deviations, got {self.sigma_v}")
        kinds = np.array([1 if m.kind == "ca" else 0 for m in self.models], dtype=np.int64)
        qvar = np.array([np.square(m.sigma_w) for m in self.models], dtype=float)
        if not self.max_gap_s > 0:
            raise PredictorError(f"max_gap_s must be a positive number of seconds, got {self.max_gap_s}")
        cfg = np.array([self.tau, self.eps_mix, self.eps_mu, float(self.adaptive_tpm),
                        MODE_WEIGHTS[self.mode_weights], H_JACOBIANS[self.h_jacobian], self.p0_omega, self.p0_alpha,
                        self.max_gap_s])
        self._config = (kinds, qvar, sigma_v**2, cfg, stationary(Pi), Pi)

    def _state(self, n_sensors: int) -> K.State:
        kinds, _, _, _, mu0, Pi0 = self._config
        M = len(kinds)
        state = K.State(np.zeros((n_sensors, M, 6)), np.zeros((n_sensors, M, 6, 6)), np.zeros((n_sensors, 3, M)),
                 np.zeros((n_sensors, 2, M, M)), np.zeros((n_sensors, 4)), np.zeros((n_sensors, 2), np.int64),
                 np.zeros((n_sensors, 6)), np.zeros((n_sensors, 4)))
        for s in range(n_sensors):
            K.reset(*(a[s] for a in state), mu0, Pi0)
        return state

    def filter(self, q: ArrayLike, valid: ArrayLike | None = None, time: ArrayLike | None = None,
               ages: bool = False) -> tuple:
        """Run over a stream: (q (F, S, 4) checked, [ω̄, ᾱ] (F, S, 6), usable (F, S), mode probabilities (F, S, M)),
        and with ``ages`` the age (F, S) s of the sample each prediction starts from (non-zero after repeats)."""
        qs, ok, _ = check_stream(q, valid)
        kinds, qvar, R, cfg, _, _ = self._config
        F, S = ok.shape
        dt = steps(check_time(time, F, self.rate_hz))
        if time is None:
            dt[1:] = self.tau  # exactly the nominal period, as the live form's default
        est = np.empty((S, F, 6))
        usable = np.empty((S, F), bool)
        mu = np.empty((S, F, len(kinds)))
        age = np.empty((S, F))
        K.run(qs, ok, dt, tuple(self._state(S)), tuple(K.Model(kinds, qvar, R, cfg)),
              tuple(K.Output(est, usable, mu, age)))
        out = (qs, est.transpose(1, 0, 2), usable.T, mu.transpose(1, 0, 2))
        return out + (age.T,) if ages else out

    def rates(self, q, valid=None, time=None):
        qs, est, usable, _ = self.filter(q, valid, time)
        out = np.where(usable[..., None], est[..., :3], np.nan)
        return as_given(out, np.ndim(q) == 2)

    def predict(self, q, horizons, valid=None, time=None):
        h = check_horizons(horizons)
        qs, est, usable, _, age = self.filter(q, valid, time, ages=True)
        alpha = est[..., 3:] if np.any(est[..., 3:]) else None
        out = np.stack([extrapolate_each(qs, est[..., :3], alpha, d + age, self.tau) for d in h])
        out[:, ~usable] = np.nan
        return as_given(out, np.ndim(q) == 2)

    #: the live form, made by :meth:`stream`
    stream_type = DQStream


#: process noise per axis of a model of ``kind`` tuned at ``λ``: Table 10, or a Tuning's ``sigma_w``
ProcessNoise = Callable[[str, float], Sequence[float]]


def table_10(kind: str, lam: float) -> tuple[float, float, float]:
    """The thesis's process-noise std per axis (rad/s² for "cv", rad/s³ for "ca") of a model tuned at ``lam``."""
    try:
        return TABLE_10[kind, lam]
    except KeyError:
        raise PredictorError(f"Table 10 has no {kind} model at λ = {lam}; it has {sorted(TABLE_10)}") from None


def _models(spec: Sequence[tuple[str, float]], sigma_w: ProcessNoise) -> list[Model]:
    return [Model(kind, tuple(float(v) for v in sigma_w(kind, lam))) for kind, lam in spec]


def dqekf_cv(rate_hz: float = 120.0, sigma_w: ProcessNoise = table_10, **options) -> DQPredictor:
    """DQ-EKF, constant velocity, 3 states (tuned at λ = 0.5)."""
    return DQPredictor(_models([("cv", 0.5)], sigma_w), rate_hz, name="dqekf-cv", **options)


def dqekf_ca(rate_hz: float = 120.0, sigma_w: ProcessNoise = table_10, **options) -> DQPredictor:
    """DQ-EKF, constant acceleration, 6 states (tuned at λ = 0.5)."""
    return DQPredictor(_models([("ca", 0.5)], sigma_w), rate_hz, name="dqekf-ca", **options)


def mmdq2(rate_hz: float = 120.0, sigma_w: ProcessNoise = table_10, **options) -> DQPredictor:
    """MMDQ2: IMM of CV1 (λ = 0.5) and CA1 (λ = 1.0), Π₀ of eq. 66."""
    return DQPredictor(_models([("cv", 0.5), ("ca", 1.0)], sigma_w), rate_hz, PI_MMDQ2, name="mmdq2", **options)


def mmdq3(rate_hz: float = 120.0, mmdq3_models: str = "cv-ca-ca", sigma_w: ProcessNoise = table_10,
          **options) -> DQPredictor:
    """MMDQ3: IMM of CV1, CA1, CA2 (λ = 0.5, 1.0, 2.0), Π₀ of eq. 65; ``mmdq3_models="cv-cv-ca"`` for CV1, CV2, CA1."""
    if mmdq3_models == "cv-ca-ca":
        spec = [("cv", 0.5), ("ca", 1.0), ("ca", 2.0)]
    elif mmdq3_models == "cv-cv-ca":
        spec = [("cv", 0.5), ("cv", 1.0), ("ca", 1.0)]
    else:
        raise PredictorError(f"mmdq3_models is 'cv-ca-ca' or 'cv-cv-ca', got {mmdq3_models!r}")
    return DQPredictor(_models(spec, sigma_w), rate_hz, PI_MMDQ3, name="mmdq3", **options)
