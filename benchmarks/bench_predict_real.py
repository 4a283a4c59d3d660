"""Prediction on real recordings (issue: head-motion prediction that holds on real recordings).

Every figure scores predictors against the recording's own later samples (slerp between its
samples at t + horizon; ``ivc.predict.recording``), geodesic error in mrad, at the recording's own
time steps. Targets, on the headset trace ``shared/data/head_motion/user1_quaternion.txt`` with the
default predictor (``auto``) and no tuning options: at 50 ms, median and 95th percentile <= 0.9 x the
better of poly1 and DQ-EKF CV (each measured here), and at 100 ms a median <= 0.5 x no prediction's;
and, the weaker requirement, at least as good as that better simple predictor (<= 1.0 x). ``direct``
(the learned member of auto's bank) alone is printed beside them, and ``auto`` without its ``combine``
member (the forecast combination, ``ivc.predict.combine``) as the reference for what that member adds.

The second check, on recordings whose motion was not used to choose anything: the Polhemus Liberty
recordings (sensor 2 turning, sensor 1 static), ``auto`` against the better of poly1 and DQ-EKF CV at
50 ms (reference rows). And the live step: ``auto``'s update + 50 ms prediction fed the headset's time
stamps against the same stream fed none (nominal steps), same process, alternating (target <= 1.1 x); and
the same step against ``auto`` without the ``combine`` member, the bank before it joined (target <= 1.1 x).
Recordings that are not there are skipped (``shared/`` sits beside the repository).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from benchmarks.harness import Figure
from ivc.collect import read_recording
from ivc.predict import make
from ivc.predict.auto import AutoPredictor
from ivc.predict.recording import score

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
HEAD = DATA / "head_motion" / "user1_quaternion.txt"
LIBERTY = DATA / "polhemus_liberty"
SIMPLE = ("poly1", "dqekf-cv")


def _better_simple(scores: dict, horizon: float, key: str) -> tuple[str, float]:
    return min(((n, scores[n].at(horizon)[key]) for n in SIMPLE), key=lambda x: x[1])


def _headset(step) -> list[Figure]:
    names = ("auto", "direct", "none", *SIMPLE)
    selection = AutoPredictor(step.sample_rate_hz, combination=False, name="auto-selection")
    scores = {s.name: s for s in score([make(n, step.sample_rate_hz) for n in names] + [selection],
                                       step.quaternion[:, 0], step.time, [0.05, 0.1])}
    figures = []
    for key in ("median", "p95"):
        auto = scores["auto"].at(0.05)[key]
        which, simple = _better_simple(scores, 0.05, key)
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", f"better simple ({which})", simple,
                              "<= 0.9x better simple", auto <= 0.9 * simple, higher_is_better=False))
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", f"better simple ({which})", simple,
                              "<= 1.0x (as good)", auto <= simple, higher_is_better=False))
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", "no prediction",
                              scores["none"].at(0.05)[key], "(reference)", None, higher_is_better=False))
        figures.append(Figure(f"headset 50 ms {key}, direct", scores["direct"].at(0.05)[key], "mrad",
                              f"better simple ({which})", simple, "(reference)", None, higher_is_better=False))
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", "auto without combine",
                              scores["auto-selection"].at(0.05)[key], "(reference)", None, higher_is_better=False))
    auto, none = scores["auto"].at(0.1)["median"], scores["none"].at(0.1)["median"]
    figures.append(Figure("headset 100 ms median, auto", auto, "mrad", "no prediction", none, "<= 0.5x none",
                          auto <= 0.5 * none, higher_is_better=False))
    which, simple = _better_simple(scores, 0.1, "median")
    figures.append(Figure("headset 100 ms median, auto", auto, "mrad", f"better simple ({which})", simple,
                          "(reference)", None, higher_is_better=False))
    figures.append(Figure("headset 100 ms median, auto", auto, "mrad", "auto without combine",
                          scores["auto-selection"].at(0.1)["median"], "(reference)", None, higher_is_better=False))
    return figures


def _live_step(step, frames: int = 1500, rounds: int = 6) -> list[Figure]:
    """auto's live step (update + 50 ms prediction, one sensor) with the stream's time stamps and without, and
    with time stamps but without the ``combine`` member."""
    q, t = step.quaternion[:frames, 0], step.time[:frames]

    def run(stamped: bool, combination: bool = True) -> float:
        s = AutoPredictor(step.sample_rate_hz, combination=combination).stream(1)
        times = []
        for k in range(frames):
            start = time.perf_counter()
            s.update(q[k:k + 1], time=t[k] if stamped else None)
            s.predict(0.05)
            times.append(time.perf_counter() - start)
        return float(np.median(times[100:]))

    run(True)  # compile
    stamped, nominal, selection = [], [], []
    for _ in range(rounds):
        stamped.append(run(True))
        nominal.append(run(False))
        selection.append(run(True, combination=False))
    a, b, c = 1e6 * min(stamped), 1e6 * min(nominal), 1e6 * min(selection)
    return [Figure("live step, auto, time stamps (median of frames)", a, "us", "no time stamps", b,
                   "<= 1.1x no stamps", a <= 1.1 * b, higher_is_better=False),
            Figure("live step, auto, time stamps (median of frames)", a, "us", "auto without combine", c,
                   "<= 1.1x without", a <= 1.1 * c, higher_is_better=False)]


def _liberty() -> list[Figure]:
    figures = []
    for path in sorted(LIBERTY.glob("*.csv")):
        step, _ = read_recording(path)
        for s, sensor in enumerate(step.names):
            scores = {x.name: x for x in score([make(n, step.sample_rate_hz) for n in ("auto", "direct", *SIMPLE)],
                                               step.quaternion[:, s], step.time, [0.05], step.valid_mask[:, s])}
            for key in ("median", "p95"):
                which, simple = _better_simple(scores, 0.05, key)
                figures.append(Figure(f"{path.stem[9:24]} s{sensor} 50 ms {key}, auto", scores["auto"].at(0.05)[key],
                                      "mrad", f"better simple ({which})", simple, "(reference)", None,
                                      higher_is_better=False))
    return figures


def run() -> list[Figure]:
    figures = []
    if HEAD.exists():
        step, _ = read_recording(HEAD)
        figures += _headset(step)
        figures += _live_step(step)
    else:
        print(f"skipped: {HEAD} is not there")
    if LIBERTY.exists():
        figures += _liberty()
    return figures
