"""Prediction filters (issue: prediction): step cost against FilterPy, batch against the per-step loop, accuracy.

Targets: DQ-EKF CV step <= 1/5 of FilterPy's ExtendedKalmanFilter running the same model;
MMDQ3 step <= 1/10 of FilterPy's IMMEstimator over three Kalman filters of the same size;
16 sensors x 100,000 frames filtered in batch: printed against the per-step loop (a step as
above: one filter, one sensor, one sample) and the loop over frames of one 16-sensor stream,
as references only (the earlier 10x target is retired: the batch runs far beyond any recording);
synthetic aggressive motion at 50 ms: MMDQ2 mean error <= 1/3 of DQ-EKF CV's; every predictor
beats no prediction by >= 3x (mean error) on moderate and aggressive motion, each filter tuned to the
synthetic tracker: Himberg 2010's filters' measurement noise, and process noise at each model's λ, from a
separate synthetic tuning set by the thesis's procedure (ivc.predict.tuning). Himberg 2010's filters with
the thesis's own values (the defaults, which describe its tracker) are printed beside them for reference.

A step of ours is a full live frame: Δq from the new orientation, the filter cycle, and the
orientation predicted 50 ms ahead. The FilterPy baselines are the filter cycle alone
(predict + update with the Jacobian evaluated in Python), which favours them.
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.harness import Figure
from ivc.predict import TUNABLE, make
from ivc.predict.delta import delta_q, delta_q_jacobian, deltas
from ivc.predict.dq import SIGMA_CA1, SIGMA_CA2, SIGMA_CV1, SIGMA_DQ, dqekf_cv, mmdq2, mmdq3
from ivc.predict.hold import NoPrediction
from ivc.predict.motion import head_motion
from ivc.predict.studies.evaluate import evaluate
from ivc.predict.tuning import synthetic

TAU = 1.0 / 120.0
#: every timing is the best of this many runs, ours and the baseline's alike (the least disturbed by other load)
REPEATS = 5
COMPARED = ("dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3", "q-ekf", "mmae", "alpha-beta", "kinematic", "poly1", "poly2",
            "direct", "auto")


def _per_step(fn, steps: int) -> float:
    start = time.perf_counter()
    for k in range(steps):
        fn(k)
    return (time.perf_counter() - start) / steps


def _filterpy_ekf(z):
    from filterpy.kalman import ExtendedKalmanFilter

    ekf = ExtendedKalmanFilter(dim_x=3, dim_z=4)
    ekf.x = np.zeros(3)
    ekf.F = np.eye(3)
    ekf.Q = TAU**2 * np.diag(np.square(SIGMA_CV1))
    ekf.R = np.diag(np.square(SIGMA_DQ))

    def step(k):
        ekf.predict()
        ekf.update(z[k], lambda x: delta_q_jacobian(x, TAU), lambda x: delta_q(x, TAU))

    return step


def _filterpy_imm(z):
    from filterpy.kalman import IMMEstimator, KalmanFilter

    filters = []
    for sigma in (SIGMA_CV1, SIGMA_CA1, SIGMA_CA2):
        kf = KalmanFilter(dim_x=6, dim_z=4)
        kf.F = np.block([[np.eye(3), TAU * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
        W = np.vstack([TAU**2 / 2 * np.eye(3), TAU * np.eye(3)])
        kf.Q = W @ np.diag(np.square(sigma)) @ W.T
        kf.R = np.diag(np.square(SIGMA_DQ))
        filters.append(kf)
    Pi = np.array([[0.970, 0.029, 0.001], [0.069, 0.917, 0.014], [0.001, 0.250, 0.749]])
    imm = IMMEstimator(filters, np.array([0.684, 0.297, 0.019]), Pi)

    def step(k):
        imm.predict()
        for kf in filters:  # the Jacobian at each filter's predicted rate, as an EKF would use
            kf.H = np.hstack([delta_q_jacobian(kf.x[:3, 0], TAU), np.zeros((4, 3))])
        imm.update(z[k] - [1.0, 0.0, 0.0, 0.0])  # linear model about ω = 0: Δq − [1, 0] ≈ J ω

    return step


def _stream_step(predictor, q):
    stream = predictor.stream(1)

    def step(k):
        stream.update(q[k:k + 1])
        stream.predict(0.05)

    return step


def run() -> list[Figure]:
    figures = []
    motion = head_motion("moderate", 12_000, seed=0)
    q = motion.measured
    z = deltas(q)
    n = 3000
    ours = min(_per_step(_stream_step(dqekf_cv(), q), n) for _ in range(REPEATS))
    theirs = min(_per_step(_filterpy_ekf(z), n) for _ in range(REPEATS))
    figures.append(Figure("DQ-EKF CV live step (update + 50 ms predict)", ours * 1e6, "us",
                          "FilterPy ExtendedKalmanFilter", theirs * 1e6, "<= 1/5 of FilterPy", ours <= theirs / 5,
                          higher_is_better=False))
    ours = min(_per_step(_stream_step(mmdq3(), q), n) for _ in range(REPEATS))
    theirs = min(_per_step(_filterpy_imm(z), n) for _ in range(REPEATS))
    figures.append(Figure("MMDQ3 live step (update + 50 ms predict)", ours * 1e6, "us",
                          "FilterPy IMMEstimator x3 KF", theirs * 1e6, "<= 1/10 of FilterPy", ours <= theirs / 10,
                          higher_is_better=False))

    sensors, frames = 16, 100_000
    q16 = np.stack([head_motion("full", frames, seed=s, dynamic_error=0.0).measured for s in range(sensors)], axis=1)

    def timed_steps(predictor, loop_frames=2_000):
        """The step the live figures time, one filter per sensor: 16 calls a frame."""
        streams = [predictor.stream(1) for _ in range(sensors)]
        start = time.perf_counter()
        for k in range(loop_frames):
            for s, stream in enumerate(streams):
                stream.update(q16[k, s:s + 1])
        return (time.perf_counter() - start) * frames / loop_frames

    def timed_frames(predictor, loop_frames=10_000):
        """One stream over all 16 sensors: one call a frame."""
        stream = predictor.stream(sensors)
        start = time.perf_counter()
        for k in range(loop_frames):
            stream.update(q16[k])
        return (time.perf_counter() - start) * frames / loop_frames

    def timed_batch(predictor):
        start = time.perf_counter()
        predictor.filter(q16)
        return time.perf_counter() - start

    for predictor in (dqekf_cv(), mmdq2()):
        predictor.filter(q16[:100])  # compile
        # best of REPEATS for every side, as for the live steps: timings on a shared VM wander by ±30 %
        batch = min(timed_batch(predictor) for _ in range(REPEATS))
        steps = min(timed_steps(predictor) for _ in range(REPEATS))
        per_frame = min(timed_frames(predictor) for _ in range(REPEATS))
        figures.append(Figure(f"{predictor.name} 16 x 100k frames, batch", batch, "s",
                              "per-step loop (extrapolated)", steps, "(reference)", None,
                              higher_is_better=False))
        figures.append(Figure(f"{predictor.name} 16 x 100k frames, batch", batch, "s",
                              "per-frame loop, 16 a call (extr.)", per_frame, "(stricter baseline)", None,
                              higher_is_better=False))

    # Accuracy. The targets apply with every filter tuned to the (synthetic) tracker: Himberg 2010's filters'
    # R and σ_w estimated by the thesis's own procedure (docs/math.md §13.1, §13.3) from a separate synthetic composite
    # set (ivc.predict.tuning; never the evaluation data); the other filters have no such tuning. The same
    # filters with the thesis's values (the defaults: Table 3 and eq. 67 R, Table 10 σ_w, which describe the
    # thesis's tracker) are printed beside them for reference.
    tuning = synthetic(20_000, 120.0, seed=0)
    errors = {}
    for name in ("moderate", "aggressive"):
        h = head_motion(name, 20_000, seed=1)
        errors[name, "none"] = evaluate(NoPrediction(), h.measured, 120.0, name).at(50.0)["mean"]
        for f in COMPARED:
            errors[name, f] = evaluate(make(f, 120.0, tuning), h.measured, 120.0, name).at(50.0)["mean"]
        for f in TUNABLE:
            errors[name, f + " thesis"] = evaluate(make(f), h.measured, 120.0, name).at(50.0)["mean"]
    for tag, target in (("", "<= 1/3 of CV"), (" thesis", "(thesis's tuning)")):
        cv, mm = errors["aggressive", "dqekf-cv" + tag], errors["aggressive", "mmdq2" + tag]
        figures.append(Figure(f"aggressive 50 ms mean error, MMDQ2{tag}", mm, "mrad", f"DQ-EKF CV{tag}", cv,
                              target, mm <= cv / 3 if not tag else None, higher_is_better=False))
    for name in ("moderate", "aggressive"):
        for f in COMPARED + tuple(f + " thesis" for f in TUNABLE):
            value, none, tuned = errors[name, f], errors[name, "none"], f in COMPARED
            figures.append(Figure(f"{name} 50 ms mean error, {f}", value, "mrad", "no prediction", none,
                                  ">= 3x better than none" if tuned else "(thesis's tuning)",
                                  none >= 3 * value if tuned else None, higher_is_better=False))
    return figures
