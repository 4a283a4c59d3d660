"""The actual time steps of an orientation stream: rate, jitter, gaps, repeated samples.

Predictors run on the stream's own time stamps (s), not on a rate inferred once. The rules,
shared by every predictor and by :func:`stream_timing`, which reports them:

* the times must increase strictly (readers drop rows that repeat a time or go back);
* a valid sample equal to the sensor's previous valid sample, to the bit, is a *repeat*: a stale
  frame, not a measurement of no motion, so it is dropped (the prediction starts from the earlier
  sample, that much older);
* invalid samples are bridged; a stretch without a valid sample longer than ``max_gap`` s
  (:data:`MAX_GAP_S` by default) is a *gap*: the filter starts again at the next valid sample,
  as at the start of the stream.

Quaternion sign flips need nothing here: every filter measures Δq = q(k) ⊗ q(k−1)* with its
scalar part made non-negative, and q and −q give the same prediction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc.errors import PredictorError

FloatArray = NDArray[np.float64]

#: the longest stretch without a valid sample that a filter bridges (s); longer ones restart it
MAX_GAP_S = 0.25


def check_time(time: ArrayLike | None, n_frames: int, rate_hz: float) -> FloatArray:
    """Frame times (s) as an array (F,): ``time``, or k / rate_hz when None; strictly increasing."""
    if time is None:
        return np.arange(n_frames) / rate_hz
    t = np.asarray(time, dtype=float)
    if t.shape != (n_frames,):
        raise PredictorError(f"time has shape {t.shape}, expected ({n_frames},): one time stamp (s) per frame")
    if not np.all(np.isfinite(t)):
        raise PredictorError(f"time stamp {int(np.flatnonzero(~np.isfinite(t))[0])} is not finite")
    back = np.flatnonzero(np.diff(t) <= 0)
    if len(back):
        k = int(back[0]) + 1
        raise PredictorError(f"the time stamps must increase: frame {k} is at {t[k]!r} s, frame {k - 1} at "
                             f"{t[k - 1]!r} s ({len(back)} such frames); drop repeated rows and sort by time first")
    return t


def steps(time: FloatArray) -> FloatArray:
    """dt (F,) s: the time since the previous frame (0 for the first)."""
    return np.diff(time, prepend=time[:1]) if len(time) else np.zeros(0)


def _last_valid_index(ok: NDArray[np.bool_]) -> NDArray[np.int64]:
    """(F, S): index of the latest valid frame before frame k, per sensor (−1 if none)."""
    F = ok.shape[0]
    idx = np.where(ok, np.arange(F)[:, None], -1)
    latest = np.maximum.accumulate(idx, axis=0)
    before = np.full_like(latest, -1)
    before[1:] = latest[:-1]
    return before


def repeats(qs: FloatArray, ok: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(F, S): valid samples equal, to the bit, to the sensor's previous valid sample."""
    prev = _last_valid_index(ok)
    has = ok & (prev >= 0)
    same = np.zeros(ok.shape, bool)
    f, s = np.nonzero(has)
    same[f, s] = np.all(qs[f, s] == qs[prev[f, s], s], axis=-1)
    return same


def restarts(time: FloatArray, ok: NDArray[np.bool_], max_gap: float = MAX_GAP_S) -> NDArray[np.bool_]:
    """(F, S): valid samples more than ``max_gap`` s after the sensor's previous valid one (the filter restarts)."""
    prev = _last_valid_index(ok)
    out = np.zeros(ok.shape, bool)
    f, s = np.nonzero(ok & (prev >= 0))
    out[f, s] = time[f] - time[prev[f, s]] > max_gap
    return out


@dataclass
class StreamTiming:
    """How a stream was sampled: its rate and jitter, and what the predictors will drop and restart at."""

    frames: int
    sensors: int
    rate_hz: float  # 1 / median step
    step_ms: tuple[float, float, float]  # 1st percentile, median, 99th percentile of the step (ms)
    jitter_ms: float  # standard deviation of the step (ms), gaps left out
    repeats: list[int]  # per sensor: samples dropped as exact repeats
    invalid: list[int]  # per sensor: invalid samples
    gaps: list[list[tuple[float, float]]] = field(default_factory=list)  # per sensor: (time s, length s) of gaps
    max_gap_s: float = MAX_GAP_S

    def summary(self) -> str:
        lo, med, hi = self.step_ms
        lines = [f"{self.frames} frames x {self.sensors} sensors at {self.rate_hz:.4g} Hz (median step {med:.3g} ms; "
                 f"1st-99th percentile {lo:.3g}-{hi:.3g} ms; jitter {self.jitter_ms:.3g} ms std)"]
        if any(self.repeats):
            lines.append(f"repeated samples dropped: {', '.join(str(n) for n in self.repeats)} (per sensor)")
        if any(self.invalid):
            lines.append(f"invalid samples skipped: {', '.join(str(n) for n in self.invalid)} (per sensor)")
        gaps = [g for sensor in self.gaps for g in sensor]
        if gaps:
            longest = max(length for _, length in gaps)
            first = ", ".join(f"{t:.3f} s (+{length:.3g} s)" for t, length in gaps[:5])
            lines.append(f"gaps over {self.max_gap_s * 1e3:g} ms, where the filters restart: {len(gaps)} "
                         f"(longest {longest:.3g} s; at {first}{', ...' if len(gaps) > 5 else ''})")
        return "\n".join(lines)


@numba.njit(cache=True)
def _normalise_samples(q, ok, out):
    """out = q normalised where ok, NaN elsewhere; NaN samples become not ok (in place).

    Returns −1, or the flat index (frame · sensors + sensor) of the first usable sample whose
    norm is off 1 by more than 1e-3.
    """
    F, S = ok.shape
    for f in range(F):
        for s in range(S):
            n2 = q[f, s, 0] ** 2 + q[f, s, 1] ** 2 + q[f, s, 2] ** 2 + q[f, s, 3] ** 2
            if ok[f, s] and np.isfinite(n2):
                n = np.sqrt(n2)
                if abs(n - 1.0) > 1e-3:
                    return f * S + s
                for i in range(4):
                    out[f, s, i] = q[f, s, i] / n
            else:
                ok[f, s] = False
                out[f, s, :] = np.nan
    return -1


def check_stream(q: ArrayLike, valid: ArrayLike | None) -> tuple[FloatArray, NDArray[np.bool_], bool]:
    """(q as (F, S, 4), valid (F, S), whether the input had no sensor axis); NaN samples become invalid."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 2
    if single:
        q = q[:, None, :]
    if q.ndim != 3 or q.shape[-1] != 4:
        raise PredictorError(f"orientations must have shape (frames, 4) or (frames, sensors, 4), got {q.shape}")
    ok = np.ones(q.shape[:2], bool)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if single and valid.ndim == 1:
            valid = valid[:, None]
        if valid.shape != q.shape[:2]:
            raise PredictorError(f"valid has shape {valid.shape}, expected {q.shape[:2]}")
        ok[:] = valid
    out = np.empty(q.shape)
    bad = _normalise_samples(np.ascontiguousarray(q), ok, out)
    if bad >= 0:
        f, s = divmod(bad, q.shape[1])
        raise PredictorError(f"orientation at frame {f}, sensor {s} is not a unit quaternion "
                             f"(norm {np.linalg.norm(q[f, s]):.6g}); pass unit quaternions [w, x, y, z]")
    q = out
    return q, ok, single


def stream_timing(time: ArrayLike, q: ArrayLike | None = None, valid: ArrayLike | None = None,
                  max_gap: float = MAX_GAP_S) -> StreamTiming:
    """The timing of a stream: ``time`` (F,) s; ``q`` (F[, S], 4) to count repeats; ``valid`` (F[, S])."""
    t = np.asarray(time, dtype=float)
    if t.ndim != 1 or len(t) < 2:
        raise PredictorError("a stream's timing needs at least 2 time stamps")
    t = check_time(t, len(t), 1.0)
    if q is None:
        ok = np.ones((len(t), 1), bool) if valid is None else np.asarray(valid, bool).reshape(len(t), -1)
        rep = np.zeros(ok.shape, bool)
    else:
        qs, ok, _ = check_stream(q, valid)
        rep = repeats(qs, ok)
    dt = np.diff(t)
    gap = restarts(t, ok, max_gap)
    prev = _last_valid_index(ok)
    gaps = [[(float(t[k]), float(t[k] - t[prev[k, s]])) for k in np.flatnonzero(gap[:, s])]
            for s in range(ok.shape[1])]
    inside = dt[dt <= max_gap]
    return StreamTiming(len(t), ok.shape[1], float(1.0 / np.median(dt)),
                        tuple(float(v) for v in 1e3 * np.percentile(dt, [1, 50, 99])),
                        float(1e3 * np.std(inside)) if len(inside) else 0.0,
                        [int(n) for n in rep.sum(axis=0)], [int(n) for n in (~ok).sum(axis=0)], gaps, max_gap)
