"""Tune Himberg 2010's Kalman predictors to a tracker from its own recordings (docs/math.md §13).

The thesis's noise values (Table 3, eq. 67) describe its Polhemus in its room. Its procedure
re-derives them from data, and this module does the same:

* **Measurement noise** (docs/math.md §13.1): the residual of the recording around a Gaussian-smoothed copy
  of itself. For the Q-EKF, q − q_smooth per quaternion component; for the DQ filters,
  Δq(raw) − Δq(smoothed q). Components are independent (R diagonal), as in the thesis. The
  smoothed copy keeps a little of the noise; each std is divided by the fraction of white
  noise its residual keeps (0.86 for q, 0.98 for Δq at the default width), so white noise is
  estimated without bias. What else the residual holds (dynamic error, the smoothing's bend
  of fast turns) counts as noise, as in the thesis.
* **The scalar part of Δq** is not an independent measurement: a unit Δq has
  z0 = √(1 − |z_v|²), so z0's noise is the vector part's, projected on the rotation
  (δz0 ≈ −z_v·δz_v / z0; on synthetic aggressive motion the two correlate at 0.9997 and z0's
  own part is 2.5 % of its std). Its estimated std, pooled over mostly slow frames where z_v ≈ 0,
  is tiny, and a diagonal R then counts the vector noise a second time, with a weight that
  grows with speed. The DQ filters are therefore given z0's std equal to the vector part's
  largest: an upper bound on its noise (|δz0| ≤ |z_v||δz_v|) that leaves z0 a weight of at
  most (|ω|τ/2)² against the vector part (below 10⁻³ up to 7 rad/s at 120 Hz), so that the
  filters take the information once, from the vector part (:attr:`Tuning.sigma_v_dq`).
* **Manoeuvring index** λ (docs/math.md §13.2): per sample, the root mean square of the smoothed angular
  velocity's frame-to-frame change over a 12-sample window centred on the sample (about zero:
  process noise has zero mean), over the std of the measured angular velocity around the
  smoothed one. Both are 3-vectors; λ uses their root-sum-square over the axes (the thesis
  does not say per axis or on norms).
* **Process noise** (docs/math.md §13.3, the scaling that reproduces Table 10): a model is defined by the λ it
  is tuned at (CV1 0.5, CA1 1.0, CA2 2.0, ...), and σ_w,CV = λ σ_Δq / τ² (rad/s²),
  σ_w,CA = λ σ_Δq / τ³ (rad/s³), σ_Δq the vector part of the DQ noise. Re-deriving σ_w with
  σ_v keeps each filter's gain, which depends on their ratio only, at the thesis's.
* **Initial transition matrix** Π₀ (docs/math.md §13.4): transitions between λ labels, counted frame to frame.

The Gaussian kernel's width is not in the thesis; the default, σ = 2 frames at 120 Hz (17 ms),
removes white noise while a head turn bends the smoothed copy by far less than the noise.
Frames within 4σ + 7 of a gap or of either end are left out (the smoothed copy, and λ's window,
reach past the stretch there).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import gaussian_filter1d, uniform_filter1d

from ivc.predict.base import FloatArray, PredictorError, check_rate, check_stream
from ivc.predict.delta import deltas, rate_from_delta
from ivc.predict.dq import SIGMA_DQ
from ivc.predict.motion import head_motion
from ivc.predict.qekf import R_QUATERNION

#: Gaussian smoothing width, seconds (2 frames at 120 Hz)
SMOOTH_S = 2.0 / 120.0
#: samples in the window of the per-sample λ (docs/math.md §13.2)
LAMBDA_WINDOW = 12
#: λ edges between the labels of MMDQ2 (CV1 | CA1) and MMDQ3 (CV1 | CA1 | CA2), from the thesis's λ ranges
EDGES_MMDQ2 = (0.75,)
EDGES_MMDQ3 = (0.75, 1.0)


@dataclass(frozen=True)
class Tuning:
    """Noise and manoeuvring statistics of one or more recordings at ``rate_hz``."""

    rate_hz: float
    smooth_s: float
    frames: int
    sigma_q: FloatArray  # (4,) std of the quaternion components' noise: the Q-EKF's sigma_v
    sigma_dq: FloatArray  # (4,) std of the Δq components' noise: the DQ filters' sigma_v
    lam_runs: tuple[FloatArray, ...]  # per-sample λ, one array per gap-free stretch

    @property
    def tau(self) -> float:
        return 1.0 / self.rate_hz

    def matches_rate(self, rate_hz: float) -> bool:
        """Whether a stream at ``rate_hz`` may use this tuning (its noise and σ_w depend on the frame time)."""
        return bool(np.isclose(self.rate_hz, rate_hz, rtol=1e-9))

    @property
    def sigma_v_dq(self) -> FloatArray:
        """(4,) the DQ filters' measurement noise: the vector part as estimated, z0 its largest std (see above)."""
        return np.concatenate([[self.sigma_dq[1:].max()], self.sigma_dq[1:]])

    @property
    def lam(self) -> FloatArray:
        """Every sample's λ (dimensionless)."""
        return np.concatenate(self.lam_runs) if self.lam_runs else np.zeros(0)

    def lambda_percentiles(self) -> dict[str, float]:
        """λ quartiles and 98th percentile, the layout of Table 8."""
        q = np.percentile(self.lam, [25, 50, 75, 98])
        return dict(zip(("q1", "median", "q3", "p98"), q.tolist(), strict=True))

    def sigma_w_cv(self, lam: float = 0.5) -> FloatArray:
        """Process noise std of a CV model tuned at ``lam`` (rad/s², per axis)."""
        return lam * self.sigma_dq[1:] / self.tau**2

    def sigma_w_ca(self, lam: float = 0.5) -> FloatArray:
        """Process noise std of a CA model tuned at ``lam`` (rad/s³, per axis)."""
        return lam * self.sigma_dq[1:] / self.tau**3

    def sigma_w(self, kind: str, lam: float) -> FloatArray:
        """Process noise std of a model of ``kind`` ("cv" or "ca") tuned at ``lam``: the DQ factories' ``sigma_w``."""
        if kind not in ("cv", "ca"):
            raise PredictorError(f"a model kind is 'cv' or 'ca', got {kind!r}")
        return self.sigma_w_cv(lam) if kind == "cv" else self.sigma_w_ca(lam)

    def transition(self, edges: Sequence[float] = EDGES_MMDQ2) -> FloatArray:
        """Π₀ (rows = from, columns = to) from the frame-to-frame changes of λ's label.

        Labels are the intervals between ``edges``. Each count starts at 1 (Laplace's rule), so a
        label the recording never leaves, or never reaches, does not get a probability of 0 or 1.
        """
        edges = np.asarray(edges, dtype=float)
        if edges.ndim != 1 or edges.size == 0 or np.any(np.diff(edges) <= 0):
            raise PredictorError(f"edges must be increasing λ values, got {edges}")
        counts = np.ones((edges.size + 1, edges.size + 1))
        for lam in self.lam_runs:
            label = np.searchsorted(edges, lam, side="right")
            np.add.at(counts, (label[:-1], label[1:]), 1.0)
        return counts / counts.sum(axis=1, keepdims=True)

    def summary(self) -> str:
        """A few lines comparing the estimates with the thesis's values."""
        pct = self.lambda_percentiles()

        def row(values):
            return "[" + ", ".join(f"{v:.3g}" for v in values) + "]"

        lines = [
            f"tuning from {self.frames} frames at {self.rate_hz:g} Hz (Gaussian σ {self.smooth_s * 1e3:.3g} ms)",
            f"  Q-EKF sigma_v (quaternion) {row(self.sigma_q)}   thesis Table 3 {row(np.sqrt(R_QUATERNION))}",
            f"  DQ    sigma_v (Δq)         {row(self.sigma_dq)}   thesis eq. 67  {row(SIGMA_DQ)}",
            f"        used by the filters  {row(self.sigma_v_dq)}   (z0 repeats the vector part's noise)",
            f"  λ quartiles {pct['q1']:.2f} / {pct['median']:.2f} / {pct['q3']:.2f}, 98th percentile "
            f"{pct['p98']:.2f}   (thesis Table 8, full range: 0.16 / 0.26 / 0.48, 1.07)",
            f"  σ_w at λ = 0.5: CV {row(self.sigma_w_cv())} rad/s², CA {row(self.sigma_w_ca())} rad/s³   "
            "(thesis Table 10: [1.48, 0.63, 0.72], [176, 76, 86])",
            "  MMDQ2 Π₀ " + row(self.transition(EDGES_MMDQ2).ravel()) + "   (thesis eq. 66: [0.971, 0.029, 0.065, "
            "0.935])",
        ]
        return "\n".join(lines)


def _runs(ok: np.ndarray, min_length: int) -> list[tuple[int, int]]:
    """[start, stop) of the stretches of True in ``ok`` at least ``min_length`` long."""
    padded = np.concatenate([[False], ok, [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return [(a, b) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= min_length]


def _sign_continuous(q: FloatArray) -> FloatArray:
    """q with each sample's sign chosen so that neighbours have a non-negative dot product (q and −q agree)."""
    flips = np.concatenate([[1.0], np.where(np.sum(q[1:] * q[:-1], axis=-1) < 0, -1.0, 1.0)])
    return q * np.cumprod(flips)[:, None]


def _white_noise_kept(sigma: float) -> tuple[float, float]:
    """Std of the residual x − smooth(x) per unit std of white noise in x, for x = q and for its differences."""
    half = int(np.ceil(4 * sigma)) + 2
    impulse = np.zeros(2 * half + 1)
    impulse[half] = 1.0
    residual = impulse - gaussian_filter1d(impulse, sigma, mode="constant")  # the residual's impulse response
    return float(np.linalg.norm(residual)), float(np.linalg.norm(np.diff(residual)) / np.sqrt(2.0))


def estimate(recordings: ArrayLike | Sequence[ArrayLike], rate_hz: float = 120.0,
             smooth_s: float = SMOOTH_S, valid: ArrayLike | Sequence[ArrayLike] | None = None) -> Tuning:
    """Tuning from one recording (frames[, sensors], 4) or a list of them (the thesis's composite set).

    ``valid`` masks samples as for the predictors (one mask per recording for a list). Every
    sensor counts as a recording of its own; invalid samples split a recording into stretches.
    """
    rate_hz = check_rate(rate_hz)
    if not (np.isfinite(smooth_s) and smooth_s > 0):
        raise PredictorError(f"the smoothing width must be a positive number of seconds, got {smooth_s}")
    is_list = isinstance(recordings, (list, tuple)) and len(recordings) > 0 and np.ndim(recordings[0]) >= 2
    items = list(recordings) if is_list else [recordings]
    masks = list(valid) if (is_list and valid is not None) else [valid] * len(items)
    if len(masks) != len(items):
        raise PredictorError(f"{len(items)} recordings but {len(masks)} validity masks")
    tau = 1.0 / rate_hz
    sigma = smooth_s * rate_hz
    keep_q, keep_dq = _white_noise_kept(sigma)
    edge = int(np.ceil(4 * sigma)) + LAMBDA_WINDOW // 2 + 1
    res_q, res_dq, res_w, spreads = [], [], [], []
    for q_in, valid_in in zip(items, masks, strict=True):
        qs, ok, _ = check_stream(q_in, valid_in)
        for s in range(qs.shape[1]):
            for a, b in _runs(ok[:, s], 2 * edge + LAMBDA_WINDOW):
                q = _sign_continuous(qs[a:b, s])
                smooth = gaussian_filter1d(q, sigma, axis=0, mode="nearest")
                smooth /= np.linalg.norm(smooth, axis=1, keepdims=True)
                dq_raw, dq_smooth = deltas(q), deltas(smooth)
                w_raw, w_smooth = rate_from_delta(dq_raw, tau), rate_from_delta(dq_smooth, tau)
                inner = slice(edge, q.shape[0] - edge)
                res_q.append((q - smooth)[inner])
                res_dq.append((dq_raw - dq_smooth)[inner])
                res_w.append((w_raw - w_smooth)[inner])
                change = np.diff(w_smooth, axis=0)  # change[j] = ω̃(j + 1) − ω̃(j)
                power = uniform_filter1d(np.sum(change**2, axis=1), LAMBDA_WINDOW)
                spreads.append(np.sqrt(power)[inner])
    if not res_q:
        raise PredictorError(f"no gap-free stretch of at least {2 * edge + LAMBDA_WINDOW} frames to tune from: "
                             "record longer, or with fewer invalid samples")
    sigma_q = np.concatenate(res_q).std(axis=0) / keep_q
    sigma_dq = np.concatenate(res_dq).std(axis=0) / keep_dq
    measurement = np.sqrt(np.sum(np.concatenate(res_w).var(axis=0))) / keep_dq
    if not (np.all(sigma_q > 0) and np.all(sigma_dq > 0) and measurement > 0):
        raise PredictorError("the recordings show no measurement noise (a simulation without noise?): "
                             "nothing to tune from")
    frames = sum(r.shape[0] for r in res_q)
    return Tuning(rate_hz, float(smooth_s), frames, sigma_q, sigma_dq, tuple(s / measurement for s in spreads))


def synthetic(frames: int = 20_000, rate_hz: float = 120.0, seed: int = 0) -> Tuning:
    """Tuning from a synthetic composite set like the thesis's (benign, moderate, aggressive, 2 x full range).

    Its recordings use seeds ``seed + 1000`` to ``seed + 1004``, so a benchmark whose recordings use
    ``seed`` never scores a filter on the data it was tuned on.
    """
    sets = ("benign", "moderate", "aggressive", "full", "full")
    return estimate([head_motion(m, frames, rate_hz, seed=seed + 1000 + i).measured for i, m in enumerate(sets)],
                    rate_hz)
