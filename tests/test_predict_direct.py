"""``direct``: the h-step-ahead predictor learned online by recursive least squares."""

from pathlib import Path

import numpy as np
import pytest

from ivc import rotations
from ivc.errors import PredictorError
from ivc.predict import make
from ivc.predict.direct import DirectPredictor
from ivc.predict.recording import future_reference, score
from ivc.predict.timing import repeats
from tests.helpers import wandering_head

HEAD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "head_motion" / "user1_quaternion.txt"


def _wander(rng, n=900):
    """A smooth random head motion at jittered 12-22 ms steps, with repeats and a few invalid samples."""
    t, q = wandering_head(rng, n)
    q[5::2] *= -1  # sign flips
    valid = np.ones(n, bool)
    valid[400:404] = False
    return t, q, valid


def _reference_direct(t, q, valid, h, lags=4, memory=3.0, prior=1.0, floor=0.1):
    """An independent implementation: NumPy features and targets (SciPy-free slerp of the scorer), a plain loop."""
    use = valid & ~repeats(q[:, None], valid[:, None])[:, 0]
    idx = np.flatnonzero(use)
    qu, tu = q[idx], t[idx]
    n, D = len(idx), 3 * lags
    phi = np.full((n, D), np.nan)
    for j in range(1, lags + 1):
        b = np.arange(j, n)
        old, new = b - j, b - j + 1
        turn = rotations.to_rotvec(rotations.multiply(rotations.conjugate(qu[old]), qu[new]))
        rate = turn / (tu[new] - tu[old])[:, None]
        phi[b, 3 * (j - 1):3 * j] = rotations.rotate(rotations.multiply(rotations.conjugate(qu[b]), qu[old]), rate)
    ref, inside, known = future_reference(t, q, use, h, known_at=True)
    y = rotations.to_rotvec(rotations.multiply(rotations.conjugate(qu), ref[idx])) / h
    frame_of = {int(f): i for i, f in enumerate(idx)}
    learn_at = {}
    for i in range(n):
        if inside[idx[i]] and np.all(np.isfinite(phi[i])):
            learn_at.setdefault(frame_of[int(known[idx[i]])], []).append(i)
    W0 = np.zeros((D, 3))
    W0[:3] = np.eye(3)
    L, B = np.zeros((D, D)), np.zeros((D, 3))
    vel = np.full((n, 3), np.nan)
    for i in range(n):
        if i:
            L *= np.exp(-(tu[i] - tu[i - 1]) / memory)
            B *= np.exp(-(tu[i] - tu[i - 1]) / memory)
        for k in learn_at.get(i, []):
            w = 1.0 / np.sqrt(phi[k, :3] @ phi[k, :3] + floor**2)
            L += w * np.outer(phi[k], phi[k])
            B += w * np.outer(phi[k], y[k])
        if np.all(np.isfinite(phi[i])):
            vel[i] = phi[i] @ np.linalg.solve(L + prior * np.eye(D), B + prior * W0)
    out = np.full((len(t), 4), np.nan)
    last = np.maximum.accumulate(np.where(use, np.arange(len(t)), -1))
    for f in np.flatnonzero(valid & (last >= 0)):
        i = frame_of[int(last[f])]
        if np.all(np.isfinite(vel[i])):
            out[f] = rotations.multiply(qu[i], rotations.from_rotvec(vel[i] * (h + t[f] - tu[i])))
    return out


def test_matches_an_independent_implementation(rng):
    t, q, valid = _wander(rng)
    for h in (0.03, 0.1):
        pred = DirectPredictor(60.0).predict(q, [h], valid, time=t)[0]
        ref = _reference_direct(t, q, valid, h)
        assert np.array_equal(np.isnan(pred), np.isnan(ref))
        assert np.nanmax(rotations.angle_between(pred, ref)) < 1e-9


def test_is_causal_and_live_equals_batch(rng):
    t, q, valid = _wander(rng)
    p = DirectPredictor(60.0, horizon_s=0.05)
    pred = p.predict(q, [0.05], valid, time=t)[0]
    changed = q.copy()
    changed[500:] = rotations.multiply(rotations.from_rotvec([0.3, -0.2, 0.1]), changed[500:])
    again = p.predict(changed, [0.05], valid, time=t)[0]
    assert np.array_equal(pred[:500], again[:500], equal_nan=True)  # nothing at t uses a sample after t
    assert not np.allclose(pred[500:], again[500:], equal_nan=True)
    stream = p.stream(1)
    live = np.empty_like(pred)
    for k in range(len(t)):
        stream.update(q[k:k + 1], valid[k:k + 1], time=t[k])
        live[k] = stream.predict(0.05)[0]
    assert np.array_equal(np.isnan(live), np.isnan(pred))
    assert np.nanmax(rotations.angle_between(live, pred)) < 1e-12


def test_learns_what_the_backward_difference_cannot(rng):
    """A 1 Hz oscillation: the mean velocity over the horizon is a linear function of the last velocities."""
    t = np.arange(0, 20.0, 1 / 60.0)
    angle = 0.4 * np.sin(2 * np.pi * t)
    q = rotations.from_rotvec(angle[:, None] * np.array([0.0, 0.0, 1.0]))
    q = rotations.multiply(q, rotations.from_rotvec(rng.normal(0, 1e-4, (len(t), 3))))
    direct, poly1 = (s.at(0.05)["median"] for s in score([make("direct", 60.0), make("poly1", 60.0)], q, t, [0.05]))
    assert direct < 0.2 * poly1


def test_refuses_bad_settings():
    for kwargs in ({"lags": 0}, {"lags": 2.5}, {"memory_s": 0.0}, {"prior": -1.0}, {"floor": np.nan},
                   {"horizon_s": 0.0}, {"horizon_s": 2.0}):
        with pytest.raises(PredictorError):
            DirectPredictor(60.0, **kwargs)
    with pytest.raises(PredictorError, match="does not come after"):
        stream = DirectPredictor(60.0).stream(1)
        stream.update(rotations.IDENTITY[None], time=1.0)
        stream.update(rotations.IDENTITY[None], time=1.0)


@pytest.mark.skipif(not HEAD.exists(), reason="shared/data is not beside the repository")
def test_on_a_real_headset_it_beats_the_simple_predictors():
    from ivc.collect import read_recording

    step, _ = read_recording(HEAD)
    scores = {s.name: s.at(0.05) for s in score([make(n, step.sample_rate_hz) for n in ("direct", "poly1", "dqekf-cv")],
                                                step.quaternion[:, 0], step.time, [0.05])}
    for key in ("median", "p95"):
        assert scores["direct"][key] < 0.97 * min(scores["poly1"][key], scores["dqekf-cv"][key])
