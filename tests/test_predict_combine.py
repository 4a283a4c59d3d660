"""Forecast combination (``ivc.predict.combine``) and ``auto``'s ``combine`` member."""

from pathlib import Path

import numpy as np
import pytest

from ivc import rotations
from ivc.errors import PredictorError
from ivc.predict import make
from ivc.predict.auto import CANDIDATES, AutoPredictor
from ivc.predict.combine import combine, ridge_for
from tests.helpers import wandering_head


def _members(rng, n=600, C=4):
    """C noisy forecasters of a smooth target turn (rad), scored at random delays of 1-5 frames; a few never."""
    t = np.cumsum(rng.uniform(0.010, 0.025, n))
    y = 0.05 * np.stack([np.sin(2 * np.pi * f * t + p) for f, p in ((0.7, 0.0), (0.4, 1.0), (1.1, 2.0))], 1)
    gains = np.array([0.0, 0.6, 1.1, 1.4])[:C]
    turns = np.stack([g * y + rng.normal(0, 0.004 * (c + 1), y.shape) for c, g in enumerate(gains)])
    known = np.arange(n) + rng.integers(1, 6, n)
    known[known >= n] = -1
    target = y + rng.normal(0, 1e-3, y.shape)
    target[::37] = np.nan  # unscored targets
    known[::53] = -1
    return t, turns, target, known


def _reference_weights(t, turns, target, known, j, horizon, memory):
    """An independent solution (3, C) at frame j, axis by axis: the equality constraint eliminated (w_C = 1 − Σ
    others) and the weighted, ridged problem (λ/3 per axis) solved by NumPy's least squares over the targets known
    by frame j."""
    C = turns.shape[0]
    out = np.empty((3, C))
    lam = np.sqrt(ridge_for(horizon) / 3)
    ridge = np.vstack([lam * np.eye(C - 1), -lam * np.ones((1, C - 1))])  # rows of sqrt(λ/3)(w − 1/C)
    ridge_rhs = np.concatenate([np.full(C - 1, lam / C), [lam * (1 / C - 1)]])
    for a in range(3):
        rows, rhs = [ridge], [ridge_rhs]
        for k in np.flatnonzero((known >= 0) & (known <= j) & np.all(np.isfinite(target), axis=1)):
            s = np.sqrt(np.exp(-(t[j] - t[known[k]]) / memory))
            rows.append(s * (turns[:C - 1, k, a] - turns[C - 1, k, a])[None])
            rhs.append([s * (target[k, a] - turns[C - 1, k, a])])
        free = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
        out[a] = np.append(free, 1.0 - free.sum())
    return out


def test_combine_equals_an_independent_least_squares(rng):
    t, turns, target, known = _members(rng)
    for horizon, memory in ((0.05, 3.0), (0.1, 0.5)):
        mixed, weights = combine(turns, target, known, t, horizon, memory)
        assert np.allclose(weights.sum(axis=2), 1.0, atol=1e-12)
        for j in (0, 3, 50, 299, 599):
            ref = _reference_weights(t, turns, target, known, j, horizon, memory)
            assert np.allclose(weights[j], ref, rtol=0, atol=1e-9), (j, weights[j], ref)
            assert np.allclose(mixed[j], np.einsum("ac,ca->a", weights[j], turns[:, j]), atol=1e-15)
    assert np.allclose(combine(turns, np.full_like(target, np.nan), known, t, 0.05)[1], 0.25)  # nothing learned


def test_combine_is_causal_and_learns_the_best_mix(rng):
    t, turns, target, known = _members(rng)
    _, weights = combine(turns, target, known, t, 0.05)
    changed = target.copy()
    late = known > 300
    changed[late] += 0.3  # targets first known after frame 300
    _, again = combine(turns, changed, known, t, 0.05)
    assert np.array_equal(weights[:301], again[:301])
    assert not np.allclose(weights[301:], again[301:])
    # members 0.6 y + noise and 1.1 y + less noise: the fit extrapolates to a gain near 1
    mixed, _ = combine(turns, target, known, t, 0.05)
    clean = np.all(np.isfinite(target), axis=1)
    err = np.linalg.norm(mixed[300:] - target[300:], axis=1)[clean[300:]]
    best = min(np.linalg.norm(turns[c, 300:] - target[300:], axis=1)[clean[300:]].mean() for c in range(4))
    assert err.mean() < 0.8 * best


def test_combine_refuses_bad_input(rng):
    t, turns, target, known = _members(rng, n=50)
    for args in ((turns[0], target, known, t), (turns, target[:10], known, t), (turns, target, known[:3], t),
                 (np.where(np.arange(50)[None, :, None] == 4, np.nan, turns), target, known, t),
                 (turns, target, np.full(50, 60), t), (turns, target, known, t[::-1])):
        with pytest.raises(PredictorError):
            combine(*args, 0.05)
    for horizon in (0.0, np.nan):
        with pytest.raises(PredictorError):
            combine(turns, target, known, t, horizon)


def test_auto_with_the_combination_is_causal(rng):
    t, q = wandering_head(rng)
    p = make("auto", 60.0)
    assert p.members == (*CANDIDATES, "combine")
    pred, weights = p.selections(q, [0.05, 0.1], time=t)
    changed = q.copy()
    changed[500:] = rotations.multiply(rotations.from_rotvec([0.3, -0.2, 0.1]), changed[500:])
    again, again_w = p.selections(changed, [0.05, 0.1], time=t)
    assert np.array_equal(pred[:, :500], again[:, :500])  # nothing at t uses a sample after t
    assert np.array_equal(weights[:, :500], again_w[:, :500])
    assert not np.allclose(pred[:, 500:], again[:, 500:])
    assert weights[0, 300:, 0, -1].max() > 0.05  # the combine member is used


def test_auto_without_the_combination_is_the_selection_alone(rng):
    t, q = wandering_head(rng, 500)
    on, off = make("auto", 60.0), AutoPredictor(60.0, combination=False)
    assert off.members == tuple(CANDIDATES)
    pred_off, w_off = off.selections(q, [0.05], time=t)
    assert w_off.shape[-1] == len(CANDIDATES)
    # the live form without the combination equals its batch
    stream = off.stream(1)
    live = np.empty((len(t), 4))
    for k in range(len(t)):
        stream.update(q[k:k + 1], time=t[k])
        live[k] = stream.predict(0.05)[0]
    assert np.nanmax(rotations.angle_between(live, pred_off[0, :, 0])) < 1e-9
    assert not np.allclose(on.predict(q, [0.05], time=t), pred_off)
    still = AutoPredictor(60.0, horizon_s=0.0).stream(1)  # scoring at 0 s: nothing to learn, equal weights, no NaN
    for k in range(200):
        still.update(q[k:k + 1], time=t[k])
    assert np.allclose(still.mix, 1.0 / len(CANDIDATES)) and np.isfinite(still.predict(0.05)).all()


HEAD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "head_motion" / "user1_quaternion.txt"


@pytest.mark.skipif(not HEAD.exists(), reason="shared/data is not beside the repository")
def test_the_combination_helps_on_a_real_headset():
    from ivc.collect import read_recording
    from ivc.predict.recording import score

    step, _ = read_recording(HEAD)
    rate = step.sample_rate_hz
    on, off = score([make("auto", rate), AutoPredictor(rate, combination=False)], step.quaternion[:, 0], step.time,
                    [0.05])
    for key in ("median", "p95"):  # measured 7.59 against 7.67 mrad, 33.49 against 33.86
        assert on.at(0.05)[key] <= 0.995 * off.at(0.05)[key]
