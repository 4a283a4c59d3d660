"""Real time steps: jitter, repeated samples, gaps that restart the filters, and their report."""

import numpy as np
import pytest

from ivc import rotations
from ivc.errors import PredictorError
from ivc.predict import make
from ivc.predict.delta import delta_q
from ivc.predict.motion import head_motion
from ivc.predict.timing import MAX_GAP_S, stream_timing

VARIABLE_STEP = ["dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3", "q-ekf", "poly1", "poly2", "direct"]


def _rotation(rng, n=400, gap_at=None, gap_s=0.0):
    """A constant angular velocity sampled at random 10-50 ms steps (and one long gap)."""
    dt = rng.uniform(0.010, 0.050, n)
    if gap_at is not None:
        dt[gap_at] = gap_s
    t = np.cumsum(dt)
    w = rng.normal(0, 1.0, 3)
    w *= 2.0 / np.linalg.norm(w)  # 2 rad/s: ~115 deg/s, a brisk head turn
    q0 = rotations.random(1, rng)[0]
    q = rotations.multiply(delta_q(w * t[:, None], 1.0), q0)
    q[1::3] *= -1  # sign flips change nothing
    return t, w, q0, q


@pytest.mark.parametrize("name", VARIABLE_STEP)
def test_constant_rate_at_random_steps_is_predicted_exactly(rng, name):
    t, w, q0, q = _rotation(rng)
    horizons = np.array([0.0, 0.05, 0.1])
    predictor = make(name, 30.0)
    pred = predictor.predict(q, horizons, time=t)
    truth = rotations.multiply(delta_q(w * (t[None, :, None] + horizons[:, None, None]), 1.0), q0)
    err = rotations.angle_between(pred[:, 12:], truth[:, 12:])
    assert np.all(np.isfinite(err))
    assert err.max() < 1e-6
    stream = predictor.stream(1)
    live = np.empty((len(t), 4))
    for k in range(len(t)):
        stream.update(q[k:k + 1], time=t[k])
        live[k] = stream.predict(0.05)[0]
    assert np.array_equal(np.isnan(live), np.isnan(pred[1]))
    assert np.nanmax(rotations.angle_between(live, pred[1])) < 1e-9


@pytest.mark.parametrize("name", VARIABLE_STEP)
def test_repeated_samples_are_dropped_not_taken_as_no_motion(rng, name):
    t, w, q0, q = _rotation(rng)
    stale = np.arange(20, len(t), 7)
    q[stale] = q[stale - 1]  # the tracker sent the previous pose again
    pred = make(name, 30.0).predict(q, [0.05], time=t)[0]
    # a repeat's prediction starts from the sample it repeats, as old as it is: still exact
    truth = rotations.multiply(delta_q(w * (t[:, None] + 0.05), 1.0), q0)
    assert rotations.angle_between(pred[12:], truth[12:]).max() < 1e-6
    timing = stream_timing(t, q)
    assert timing.repeats == [len(stale)]


@pytest.mark.parametrize("name", ["dqekf-cv", "mmdq2", "poly1", "q-ekf", "kinematic", "direct", "nasa-ekf"])
def test_a_long_gap_restarts_the_filter_and_is_reported(rng, name):
    t, w, q0, q = _rotation(rng, gap_at=200, gap_s=2.0)
    predictor = make(name, 30.0)
    pred = predictor.predict(q, [0.05], time=t)[0]
    assert np.all(np.isfinite(pred[150:200])) and np.all(np.isfinite(pred[260:]))
    if name != "kinematic":  # a steady-state design predicts from its first sample on
        assert np.all(np.isnan(pred[200]))  # the first sample after the gap: the filter starts again
    if name != "mmdq2":  # an IMM keeps its mode probabilities: the others are a fresh filter after the gap
        fresh = make(name, 30.0).predict(q[200:], [0.05], time=t[200:])[0]
        assert np.array_equal(np.isnan(pred[200:]), np.isnan(fresh))
        assert np.nanmax(rotations.angle_between(pred[200:], fresh)) < 1e-9  # q and −q alike
    stream = predictor.stream(1)
    for k in range(len(t)):
        stream.update(q[k:k + 1], time=t[k])
    assert stream.restarts == 1
    timing = stream_timing(t, q)
    assert len(timing.gaps[0]) == 1
    start, length = timing.gaps[0][0]
    assert start == t[200] and length == pytest.approx(2.0)
    assert "gaps over 250 ms, where the filters restart: 1" in timing.summary()


def test_a_short_dropout_is_bridged():
    """Invalid samples shorter than the longest gap: the next Δq spans them and the estimate carries on."""
    h = head_motion("moderate", 600, seed=5)
    valid = np.ones(600, bool)
    valid[300:310] = False  # 83 ms at 120 Hz
    assert 10 / 120 < MAX_GAP_S
    stream = make("dqekf-cv").stream(1)
    for k in range(600):
        stream.update(h.measured[k:k + 1], valid[k:k + 1])
        if k == 310:
            assert stream.ready[0]
    assert stream.restarts == 0


def test_timing_report_and_bad_times():
    t = np.cumsum(np.r_[0.0, np.full(99, 0.01)])
    t[50:] += 0.004
    timing = stream_timing(t)
    assert timing.rate_hz == pytest.approx(100.0)
    assert timing.step_ms[2] == pytest.approx(10.0, abs=0.5) and timing.jitter_ms > 0
    with pytest.raises(PredictorError, match="frame 3 is at"):
        make("mmdq2").predict(rotations.random(5, 0), 0.05, time=[0, 1, 2, 2, 3])
    stream = make("mmdq2").stream(1)
    stream.update(rotations.random(1, 0), time=1.0)
    with pytest.raises(PredictorError, match="does not come after"):
        stream.update(rotations.random(1, 1), time=1.0)


def test_the_nasa_ekf_runs_on_the_actual_steps(rng):
    """Its cycle spans each actual step (Φ = expm(hF), W_r scaled by h / τ): once converged, exact; repeats dropped."""
    t, w, q0, q = _rotation(rng)
    q[40::9] = q[39::9][: len(q[40::9])]  # stale frames
    predictor = make("nasa-ekf", 30.0)
    pred = predictor.predict(q, [0.05], time=t)[0]
    truth = rotations.multiply(delta_q(w * (t[:, None] + 0.05), 1.0), q0)
    assert rotations.angle_between(pred[100:], truth[100:]).max() < 1e-6
    stream = predictor.stream(1)
    live = np.empty((len(t), 4))
    for k in range(len(t)):
        stream.update(q[k:k + 1], time=t[k])
        live[k] = stream.predict(0.05)[0]
    assert np.array_equal(np.isnan(live), np.isnan(pred))
    assert np.nanmax(rotations.angle_between(live, pred)) < 1e-9


@pytest.mark.parametrize("name", ["alpha-beta", "kinematic"])
def test_the_steady_state_designs_run_on_the_actual_steps(rng, name):
    """Fed time stamps, the α-β and kinematic filters are the time-varying Kalman filters of their models: the
    steady-state filter at steps of exactly 1 / rate_hz, exact on a constant rotation at random steps once settled."""
    predictor = make(name, 30.0)
    t, w, q0, q = _rotation(rng)
    q[40::9] = q[39::9][: len(q[40::9])]  # stale frames
    pred = predictor.predict(q, [0.05], time=t)[0]
    truth = rotations.multiply(delta_q(w * (t[:, None] + 0.05), 1.0), q0)
    assert rotations.angle_between(pred[100:], truth[100:]).max() < 1e-6
    stream = predictor.stream(1)
    live = np.empty((len(t), 4))
    for k in range(len(t)):
        stream.update(q[k:k + 1], time=t[k])
        live[k] = stream.predict(0.05)[0]
    assert np.nanmax(rotations.angle_between(live, pred)) < 1e-9
    uniform = np.arange(300) / 30.0
    turning = rotations.multiply(delta_q(np.sin(uniform)[:, None] * w, 1.0), q0)
    steady = predictor.predict(turning, [0.05])[0]  # no time stamps: the steady-state filter
    assert np.max(rotations.angle_between(predictor.predict(turning, [0.05], time=uniform)[0], steady)) < 1e-12


def test_mmae_runs_on_the_actual_steps(rng):
    """Fed time stamps, each MMAE cycle is over the actual step (Φ, Qd by Van Loan there): on jittered samples as
    accurate as on uniform ones, where the nominal step is 8x worse; the nominal step itself is unchanged."""
    def motion(t):
        return rotations.from_rotvec(np.stack([0.8 * np.sin(1.3 * t), 0.5 * np.sin(0.7 * t + 1), 0.3 * np.cos(2.1 * t)],
                                              axis=1))

    dt = rng.uniform(0.010, 0.030, 1500)
    jittered, uniform = np.cumsum(dt), np.arange(1, 1501) * dt.mean()
    predictor = make("mmae", 1.0 / dt.mean())
    errors = {}
    for label, t in (("jittered", jittered), ("uniform", uniform)):
        q, truth = motion(t), motion(t + 0.05)
        errors[label] = np.median(rotations.angle_between(predictor.predict(q, [0.05], time=t)[0], truth)[100:])
        errors[label, "nominal"] = np.median(rotations.angle_between(predictor.predict(q, [0.05])[0], truth)[100:])
    assert errors["jittered"] < 1.1 * errors["uniform"]
    assert errors["jittered", "nominal"] > 5 * errors["jittered"]
    q = motion(uniform)
    assert np.max(rotations.angle_between(predictor.predict(q, [0.05], time=uniform)[0],
                                          predictor.predict(q, [0.05])[0])) < 1e-12
    t, q = jittered[:400].copy(), motion(jittered[:400])
    t[200:] += 2.0  # a gap: restarts, reported
    q[50::9] = q[49::9][: len(q[50::9])]  # stale frames
    pred = predictor.predict(q, [0.05], time=t)[0]
    fresh = predictor.predict(q[200:], [0.05], time=t[200:])[0]
    assert np.nanmax(rotations.angle_between(pred[200:], fresh)) < 1e-12
    stream = predictor.stream(1)
    live = np.empty((len(t), 4))
    for k in range(len(t)):
        stream.update(q[k:k + 1], time=t[k])
        live[k] = stream.predict(0.05)[0]
    assert np.array_equal(np.isnan(live), np.isnan(pred))
    assert np.nanmax(rotations.angle_between(live, pred)) < 1e-9
    assert stream.restarts == 1
