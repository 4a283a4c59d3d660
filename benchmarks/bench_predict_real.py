"""Prediction on real recordings (issue: head-motion prediction that holds on real recordings).

Every figure scores predictors against the recording's own later samples (slerp between its
samples at t + horizon; ``ivc.predict.recording``), geodesic error in mrad, at the recording's own
time steps. Targets, on the headset trace ``shared/data/head_motion/user1_quaternion.txt`` with the
default predictor (``auto``) and no tuning options: at 50 ms, median and 95th percentile <= 0.9 x the
better of poly1 and DQ-EKF CV (each measured here), and at 100 ms a median <= 0.5 x no prediction's;
and, the weaker requirement, at least as good as that better simple predictor (<= 1.0 x). The Polhemus
Liberty recordings (sensor 2 turning, sensor 1 static) are printed beside them for reference: ``auto``
against the best single filter of its bank on each. Recordings that are not there are skipped
(``shared/`` sits beside the repository).
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.harness import Figure
from ivc.collect import read_recording
from ivc.predict import make
from ivc.predict.auto import CANDIDATES
from ivc.predict.recording import score

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
HEAD = DATA / "head_motion" / "user1_quaternion.txt"
LIBERTY = DATA / "polhemus_liberty"


def _headset() -> list[Figure]:
    step, _ = read_recording(HEAD)
    names = ("auto", "none", "poly1", "dqekf-cv")
    scores = {s.name: s for s in score([make(n, step.sample_rate_hz) for n in names], step.quaternion[:, 0],
                                       step.time, [0.05, 0.1])}
    figures = []
    for key in ("median", "p95"):
        auto = scores["auto"].at(0.05)[key]
        simple = min(scores["poly1"].at(0.05)[key], scores["dqekf-cv"].at(0.05)[key])
        which = "poly1" if scores["poly1"].at(0.05)[key] <= scores["dqekf-cv"].at(0.05)[key] else "dqekf-cv"
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", f"better simple ({which})", simple,
                              "<= 0.9x better simple", auto <= 0.9 * simple, higher_is_better=False))
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", f"better simple ({which})", simple,
                              "<= 1.0x (as good)", auto <= simple, higher_is_better=False))
        none = scores["none"].at(0.05)[key]
        figures.append(Figure(f"headset 50 ms {key}, auto", auto, "mrad", "no prediction", none, "(reference)",
                              None, higher_is_better=False))
    auto, none = scores["auto"].at(0.1)["median"], scores["none"].at(0.1)["median"]
    figures.append(Figure("headset 100 ms median, auto", auto, "mrad", "no prediction", none, "<= 0.5x none",
                          auto <= 0.5 * none, higher_is_better=False))
    return figures


def _liberty() -> list[Figure]:
    figures = []
    for path in sorted(LIBERTY.glob("*.csv")):
        step, _ = read_recording(path)
        for s, sensor in enumerate(step.names):
            bank = [CANDIDATES[c](step.sample_rate_hz) for c in CANDIDATES]
            scores = score([make("auto", step.sample_rate_hz), *bank], step.quaternion[:, s], step.time, [0.05],
                           step.valid_mask[:, s])
            best = min(scores[1:], key=lambda x: x.at(0.05)["median"])
            figures.append(Figure(f"{path.stem[9:24]} s{sensor} 50 ms median, auto", scores[0].at(0.05)["median"],
                                  "mrad", f"best single ({best.name})", best.at(0.05)["median"], "(reference)",
                                  None, higher_is_better=False))
    return figures


def run() -> list[Figure]:
    figures = []
    if HEAD.exists():
        figures += _headset()
    else:
        print(f"skipped: {HEAD} is not there")
    if LIBERTY.exists():
        figures += _liberty()
    return figures
