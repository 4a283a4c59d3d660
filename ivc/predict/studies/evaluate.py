"""Prediction error against time-shifted truth: the metrics and tables of the thesis (docs/math.md §14.1), a study.

The product's baseline (:class:`~ivc.predict.hold.NoPrediction`) lives in :mod:`ivc.predict`,
which does not import this module.

The prediction made at frame k for δ = nτ ahead is compared with the orientation at frame
k + n: by default the *measured* one (as the thesis does), or the noiseless truth of a
synthetic recording. Per-sample error (mrad):

* ``compound``: √(Δaz² + Δel² + Δroll²) of wrapped Euler-angle differences (the thesis's
  "compound angle"; ambiguous there; docs/math.md §14.1 gives this reading). Azimuth,
  elevation and roll are taken about x, y, z: the order of the thesis's ω components and of
  its tuning (Table 10, eq. 67), which the synthetic motion follows too (docs/math.md §11.1 flags the
  mapping as unspecified);
* ``geodesic``: the rotation angle between the two orientations.

Summary per (filter, horizon): mean, median, std, max, overshoot % (samples above 17.45 mrad,
1°), OS avg / OS median (over overshooting samples, 0 if none), OS max (largest overshoot,
0 if none), output SNR (dB: the smoothed output's motion power over the power of output minus
smoothed output) and the angular-velocity error for filters that estimate ω.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d

from ivc import rotations
from ivc.predict.base import Predictor

FloatArray = NDArray[np.float64]

OVERSHOOT_MRAD = 17.45
#: horizons of the thesis: 0-14 frames at 120 Hz (0-116.7 ms)
HORIZONS_MS = tuple(1000.0 * n / 120.0 for n in range(15))
#: seconds discarded at the start (filter transients; Kyger discards 0.5 s)
WARMUP_S = 0.5
#: Gaussian smoothing width (frames at 120 Hz) for SNR; the thesis does not give one
SMOOTH_FRAMES = 3.0


def euler_angles(q: FloatArray) -> FloatArray:
    """Azimuth (about x), elevation (y), roll (z) in rad, intrinsic X-Y-Z, shape (..., 3)."""
    flat = q.reshape(-1, 4)
    good = np.all(np.isfinite(flat), axis=1)
    out = np.full((flat.shape[0], 3), np.nan)
    if np.any(good):
        out[good] = rotations.to_scipy(flat[good]).as_euler("XYZ")
    return out.reshape(q.shape[:-1] + (3,))


def compound_error(predicted: FloatArray, truth: FloatArray) -> FloatArray:
    """√(Δaz² + Δel² + Δroll²) (rad) with differences wrapped to (−π, π]."""
    d = euler_angles(predicted) - euler_angles(truth)
    d = (d + np.pi) % (2 * np.pi) - np.pi
    return np.sqrt(np.sum(d**2, axis=-1))


def snr_db(predicted: FloatArray, rate_hz: float) -> float:
    """Output SNR (dB): Euler angles smoothed (Gaussian) vs the residual jitter around them."""
    e = np.unwrap(euler_angles(predicted), axis=0)
    e = e[np.all(np.isfinite(e), axis=1)]
    smooth = gaussian_filter1d(e, SMOOTH_FRAMES * rate_hz / 120.0, axis=0)
    signal = smooth - smooth.mean(axis=0)
    noise = e - smooth
    return float(10.0 * np.log10(np.sum(signal**2) / max(np.sum(noise**2), 1e-300)))


def summarise(err_mrad: FloatArray) -> dict[str, float]:
    """The per-horizon figures of Tables 5-6 and 12-15 from per-sample errors (mrad)."""
    e = err_mrad[np.isfinite(err_mrad)]
    over = e[e > OVERSHOOT_MRAD]
    return {"mean": float(e.mean()), "median": float(np.median(e)), "std": float(e.std()), "max": float(e.max()),
            "os_pct": 100.0 * over.size / e.size, "os_avg": float(over.mean()) if over.size else 0.0,
            "os_median": float(np.median(over)) if over.size else 0.0,
            "os_max": float(over.max()) if over.size else 0.0, "n": int(e.size)}


@dataclass
class Evaluation:
    """Results of one predictor on one recording: ``rows[h]`` the summary at ``horizons_ms[h]``."""

    name: str
    motion: str
    horizons_ms: FloatArray
    rows: list[dict[str, float]]
    velocity: dict[str, float] | None

    def at(self, horizon_ms: float) -> dict[str, float]:
        return self.rows[int(np.argmin(np.abs(self.horizons_ms - horizon_ms)))]


def evaluate(predictor: Predictor, measured: FloatArray, rate_hz: float, motion: str = "",
             truth: FloatArray | None = None, omega_true: FloatArray | None = None,
             horizons_ms: Sequence[float] = HORIZONS_MS, error: str = "compound") -> Evaluation:
    """Evaluate ``predictor`` on one stream (F, 4); horizons are rounded to whole frames of the stream.

    ``truth`` (F, 4) replaces the time-shifted measurements as the reference when given.
    """
    steps = np.round(np.asarray(horizons_ms) * 1e-3 * rate_hz).astype(int)
    reference = measured if truth is None else truth
    predictions = predictor.predict(measured, steps / rate_hz)
    start = int(WARMUP_S * rate_hz)
    rows = []
    measure = compound_error if error == "compound" else rotations.angle_between
    for h, n in enumerate(steps):
        end = len(measured) - n
        err = 1e3 * measure(predictions[h, start:end], reference[start + n:end + n])
        row = summarise(err)
        row["snr_db"] = snr_db(predictions[h, start:end], rate_hz)
        rows.append(row)
    velocity = None
    rates = predictor.rates(measured) if omega_true is not None else None  # a second filter pass: only if wanted
    if rates is not None:
        # the DQ state is the mean rate over the frame that just ended: compare with ω over (k−1, k)
        err = 1e3 * np.linalg.norm(rates[start:] - omega_true[start - 1:-1], axis=1)
        err = err[np.isfinite(err)]
        velocity = {"mean": float(err.mean()), "median": float(np.median(err)), "max": float(err.max())}
    return Evaluation(predictor.name, motion, steps * 1000.0 / rate_hz, rows, velocity)


def overshoot_table(results: list[Evaluation], horizon_ms: float = 50.0) -> str:
    """Table 5 layout: overshoot % per filter (rows) and motion (columns)."""
    motions = list(dict.fromkeys(r.motion for r in results))
    names = list(dict.fromkeys(r.name for r in results))
    lines = [f"% overshoot (> {OVERSHOOT_MRAD} mrad) at {horizon_ms:g} ms",
             f"{'filter':<12}" + "".join(f"{m:>12}" for m in motions)]
    for n in names:
        cells = [next((r.at(horizon_ms)["os_pct"] for r in results if r.name == n and r.motion == m), np.nan)
                 for m in motions]
        lines.append(f"{n:<12}" + "".join(f"{c:>12.2f}" for c in cells))
    return "\n".join(lines)


def _motion_table(title: str, results: list[Evaluation], columns: Sequence[tuple[str, int, str]],
                  values: Callable[[Evaluation], Sequence[float] | None]) -> str:
    """A table with one group of ``columns`` (header, width, format) per motion, each motion's name
    centred over its group, and one row per filter; ``values`` gives one evaluation's numbers for
    its group, or None (a filter with no numbers anywhere gets no row, a missing group stays blank)."""
    motions = list(dict.fromkeys(r.motion for r in results))
    names = list(dict.fromkeys(r.name for r in results if values(r) is not None))
    total = sum(w for _, w, _ in columns)
    lines = [title, f"{'':<12}" + "".join(f"{m:^{total}}" for m in motions).rstrip(),
             f"{'filter':<12}" + "".join(f"{c:>{w}}" for _ in motions for c, w, _ in columns)]
    for n in names:
        cells = ""
        for m in motions:
            r = next((r for r in results if r.name == n and r.motion == m), None)
            numbers = None if r is None else values(r)
            cells += (" " * total if numbers is None
                      else "".join(f"{x:>{w}{f}}" for x, (_, w, f) in zip(numbers, columns, strict=True)))
        lines.append(f"{n:<12}{cells}")
    return "\n".join(lines)


def error_table(results: list[Evaluation], horizon_ms: float = 50.0) -> str:
    """Table 6 layout: average error, OS avg, OS max (mrad) per motion."""
    return _motion_table(f"prediction error (mrad) at {horizon_ms:g} ms", results,
                         (("avg", 9, ".2f"), ("OS avg", 8, ".1f"), ("OS max", 8, ".1f")),
                         lambda r: [r.at(horizon_ms)[k] for k in ("mean", "os_avg", "os_max")])


def horizon_table(results: list[Evaluation], motion: str, horizons_ms: Sequence[float] = (50.0, 75.0, 100.0)) -> str:
    """Tables 12-15 layout for one motion: median, OS median, OS max (overall max), stdev per horizon (mrad)."""
    names = [r.name for r in results if r.motion == motion]
    head = "".join(f"{f'{h:g} med':>9}{'OSmed':>7}{'OSmax':>7}{'sd':>6}" for h in horizons_ms)
    lines = [f"{motion} motion, error (mrad)", f"{'filter':<12}{head}"]
    for n in names:
        r = next(r for r in results if r.name == n and r.motion == motion)
        cells = "".join(f"{r.at(h)['median']:>9.2f}{r.at(h)['os_median']:>7.1f}{r.at(h)['max']:>7.1f}"
                        f"{r.at(h)['std']:>6.2f}" for h in horizons_ms)
        lines.append(f"{n:<12}{cells}")
    return "\n".join(lines)


def velocity_table(results: list[Evaluation]) -> str:
    """Table 11 layout: angular-velocity error mean / median / max (mrad/s) per motion."""
    return _motion_table("angular-velocity error (mrad/s)", results,
                         (("mean", 8, ".1f"), ("med", 7, ".1f"), ("max", 7, ".0f")),
                         lambda r: None if not r.velocity else [r.velocity[k] for k in ("mean", "median", "max")])


def snr_table(results: list[Evaluation], horizons_ms: Sequence[float] = (0.0, 50.0, 100.0)) -> str:
    """Output SNR (dB) per filter and motion at a few horizons (the thesis's Figs. 16-17 as numbers)."""
    return _motion_table("output SNR (dB) at horizons (ms)", results, [(f"{h:g}", 7, ".1f") for h in horizons_ms],
                         lambda r: [r.at(h)["snr_db"] for h in horizons_ms])


#: errors below this (mrad) are exact zeros up to rounding (a filter returning the measurement at 0 ms)
PLOT_FLOOR_MRAD = 1e-6


def plot_error_vs_horizon(results: list[Evaluation], path, metric: str = "mean") -> None:
    """One column per motion: ``metric`` error (mrad, log axis) and output SNR (dB) against horizon (ms); PNG.

    Errors of zero (to rounding) are left off the log axis, which starts just below the smallest other one.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    motions = list(dict.fromkeys(r.motion for r in results))
    fig, axes = plt.subplots(2, len(motions), figsize=(4.2 * len(motions), 6.6), squeeze=False, sharex=True)
    for column, m in enumerate(motions):
        ax_error, ax_snr = axes[0, column], axes[1, column]
        lowest = np.inf
        for r in (r for r in results if r.motion == m):
            style = "k--" if r.name == "none" else "-"
            error = np.array([row[metric] for row in r.rows])
            error = np.where(error > PLOT_FLOOR_MRAD, error, np.nan)
            lowest = min(lowest, np.nanmin(error, initial=np.inf))
            ax_error.plot(r.horizons_ms, error, style, marker=".", label=r.name)
            ax_snr.plot(r.horizons_ms, [row["snr_db"] for row in r.rows], style, marker=".", label=r.name)
        ax_error.set_title(f"{m} motion")
        ax_error.set_yscale("log")
        if np.isfinite(lowest):
            ax_error.set_ylim(bottom=0.5 * lowest)
        ax_snr.set_xlabel("prediction horizon (ms)")
        for ax in (ax_error, ax_snr):
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel(f"{metric} compound angular error (mrad)")
    axes[1, 0].set_ylabel("output SNR (dB)")
    axes[0, -1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
