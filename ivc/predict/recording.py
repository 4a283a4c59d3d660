"""Scoring predictors on a real recording against its own later samples (``ivc predict INPUT --evaluate``).

A prediction made at frame k for horizon h is compared with the recording's orientation at
t(k) + h, interpolated by slerp between the two samples around that time. The reference
samples are the valid ones that are not exact repeats (a repeat is a stale frame: its time is
not the time of its orientation). Left out of the score, for every predictor alike:

* frames in the first :data:`WARMUP_S` s (filter start-up);
* frames whose reference lies past the end, or between two samples more than ``max_step`` s
  apart (:data:`REFERENCE_MAX_STEP_S`: no trustworthy orientation there);
* invalid frames.

Where a predictor has no prediction (its first samples, after a restart), the orientation shown
is the measured one, as ``ivc predict`` writes it, and that is what is scored. The error is the
geodesic angle between prediction and reference (mrad); each predictor gets the median, 95th
percentile, RMS and mean per horizon.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc import rotations
from ivc.errors import PredictorError
from ivc.predict.base import Predictor, check_horizons, check_stream
from ivc.predict.timing import check_time, repeats

FloatArray = NDArray[np.float64]

#: start-up left out of the score (s)
WARMUP_S = 0.5
#: a reference interpolated between samples further apart than this (s) is left out
REFERENCE_MAX_STEP_S = 0.040
#: the horizons scored when none are asked for (s)
DEFAULT_HORIZONS = (0.025, 0.05, 0.075, 0.1)


def slerp(q0: FloatArray, q1: FloatArray, u: FloatArray) -> FloatArray:
    """Spherical linear interpolation (..., 4) from q0 (u = 0) to q1 (u = 1) along the shorter arc."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    dq = rotations.multiply(q1, rotations.conjugate(q0))
    return rotations.multiply(rotations.from_rotvec(u[..., None] * rotations.to_rotvec(dq)), q0)


def future_reference(time: FloatArray, q: FloatArray, usable: NDArray[np.bool_], horizon: float,
                     max_step: float = REFERENCE_MAX_STEP_S, known_at: bool = False) -> tuple:
    """The recording's orientation (F, 4) at time[k] + horizon, slerped between the usable samples around it,
    and where it exists (F,): inside the recording, between samples at most ``max_step`` s apart. With
    ``known_at``, also the frame (F,) at which that reference is first known (its later sample's frame)."""
    frames = np.flatnonzero(usable)
    t, knots = time[usable], q[usable]
    if len(t) == 0:
        nothing = np.zeros(len(time), bool)
        out = (np.full((len(time), 4), np.nan), nothing)
        return out + (np.full(len(time), -1),) if known_at else out
    target = time + horizon
    right = np.searchsorted(t, target, side="left")  # t[right - 1] < target <= t[right]
    exact = (right < len(t)) & (t[np.minimum(right, len(t) - 1)] == target)
    left = np.where(exact, right, right - 1)
    inside = (left >= 0) & (right < len(t))
    lo, hi = np.clip(left, 0, len(t) - 1), np.clip(right, 0, len(t) - 1)
    span = t[hi] - t[lo]
    inside &= span <= max_step
    u = np.where(span > 0, (target - t[lo]) / np.where(span > 0, span, 1.0), 0.0)
    out = slerp(knots[lo], knots[hi], u)
    out[~inside] = np.nan
    if known_at:
        return out, inside, np.where(inside, frames[hi], -1)
    return out, inside


@dataclass
class Score:
    """One predictor's errors (mrad) on one recording: ``rows[h]`` the summary at ``horizons_s[h]``."""

    name: str
    horizons_s: FloatArray
    rows: list[dict[str, float]]

    def at(self, horizon_s: float) -> dict[str, float]:
        return self.rows[int(np.argmin(np.abs(self.horizons_s - horizon_s)))]


def _summary(err: FloatArray) -> dict[str, float]:
    return {"median": float(np.median(err)), "p95": float(np.percentile(err, 95)),
            "rms": float(np.sqrt(np.mean(err**2))), "mean": float(np.mean(err)), "n": int(err.size)}


def score(predictors: Sequence[Predictor], q: ArrayLike, time: ArrayLike, horizons: Sequence[float] = DEFAULT_HORIZONS,
          valid: ArrayLike | None = None, max_step: float = REFERENCE_MAX_STEP_S,
          progress=None) -> list[Score]:
    """Every predictor on one sensor's recording q (F, 4) at ``time`` (F,) s, scored against its own future.

    ``progress``: called with 1 after each predictor (e.g. a tqdm bar's update).
    """
    h = check_horizons(horizons)
    qs, ok, _ = check_stream(q, valid)
    if qs.shape[1] != 1:
        raise PredictorError(f"score one sensor at a time: got {qs.shape[1]} sensors")
    t = check_time(time, qs.shape[0], 1.0)
    if t[-1] - t[0] < 2 * WARMUP_S + h.max():
        raise PredictorError(f"the recording lasts {t[-1] - t[0]:.3g} s: too short to score predictions "
                             f"{h.max() * 1e3:g} ms ahead (at least {2 * WARMUP_S + h.max():.3g} s)")
    measured, ok1 = qs[:, 0], ok[:, 0]
    usable = ok1 & ~repeats(qs, ok)[:, 0]
    references = [future_reference(t, measured, usable, d, max_step) for d in h]
    keep = [ok1 & inside & (t >= t[0] + WARMUP_S) for _, inside in references]
    if not any(k.any() for k in keep):
        raise PredictorError("no frame of the recording can be scored: every reference falls in a gap")
    out = []
    for predictor in predictors:
        predicted = predictor.predict(qs, h, ok, time=t)[:, :, 0]
        shown = np.where(np.all(np.isfinite(predicted), axis=-1, keepdims=True), predicted, measured[None])
        rows = []
        for i, (reference, _) in enumerate(references):
            err = 1e3 * rotations.angle_between(shown[i, keep[i]], reference[keep[i]])
            rows.append(_summary(err))
        out.append(Score(predictor.name, h, rows))
        if progress is not None:
            progress(1)
    return out


def table(scores: Sequence[Score]) -> str:
    """median / p95 / RMS (mrad) per predictor (rows) and horizon (column groups)."""
    horizons = scores[0].horizons_s
    width = 22
    head = f"{'filter':<14}" + "".join(f"{f'{1e3 * d:g} ms':^{width}}" for d in horizons)
    sub = f"{'':<14}" + "".join(f"{'median':>8}{'p95':>7}{'RMS':>7}" for _ in horizons)
    lines = ["prediction error against the recording's own future (geodesic, mrad)", head.rstrip(), sub]
    for s in scores:
        lines.append(f"{s.name:<14}" + "".join(f"{r['median']:>8.2f}{r['p95']:>7.1f}{r['rms']:>7.1f}" for r in s.rows))
    lines.append(f"frames scored per horizon: {', '.join(str(r['n']) for r in scores[0].rows)}")
    return "\n".join(lines)


def plot(scores: Sequence[Score], path, title: str = "") -> None:
    """Median and 95th-percentile error (mrad) against horizon (ms), one line per predictor; PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.5, 4.0), sharex=True)
    colours = plt.get_cmap("tab20")
    for i, s in enumerate(scores):
        style = {"color": "k", "linestyle": "--"} if s.name == "none" else {"color": colours(i % 20)}
        width = 2.5 if s.name == "auto" else 1.2
        for ax, key in zip(axes, ("median", "p95"), strict=True):
            ax.plot(1e3 * s.horizons_s, [r[key] for r in s.rows], marker=".", linewidth=width, label=s.name, **style)
    for ax, key in zip(axes, ("median", "95th percentile"), strict=True):
        ax.set_xlabel("prediction horizon (ms)")
        ax.set_ylabel(f"{key} error (mrad)")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
