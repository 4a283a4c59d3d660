"""The HIGH_RESIDUAL test scaled to the table's model error and the signal noise (issue 38, ivc.correct.residual_gate)
"""

from dataclasses import replace

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.correct import HIGH_RESIDUAL, Corrector
from ivc.correct.residual_gate import MAX_RESIDUAL, RESIDUAL_SIGMAS, ResidualGate
from ivc.errors import InputError
from ivc.lut.samples import leverage
from tests.helpers import ball, quadratic_field


def _with_record(table, cv_mm=None, sigma=None):
    fit = {}
    if cv_mm is not None:
        fit["cv_rms_mm"] = cv_mm
    if sigma is not None:
        fit["signal_noise"] = {"sigma": sigma}
    return replace(table, fit=fit)


def test_white_noise_alone_leaves_the_residual_the_gate_expects(exact_table, rng):
    """With a perfect table, the residual of signals with white noise σ per entry is √(χ²₃ σ²)/|S|_F: its median
    over many poses is √(2.366/3) = 0.888 of the gate's expected residual, whatever the range."""
    sigma = 2e-3
    r = ball(rng, 4000, 0.18)
    T = rotations.to_matrix(rotations.random(len(r), rng))
    S = dipole.signal(r, T, quadratic_field(r)) + sigma * rng.standard_normal((len(r), 3, 3))
    table = _with_record(exact_table, cv_mm=1e-9, sigma=sigma)  # no model error to speak of
    corrector = Corrector(table)
    out = corrector.batch(S)
    ratio = out.residual / corrector.residual_gate.expected(S, out.position)
    assert np.median(ratio) == pytest.approx(np.sqrt(2.366 / 3), rel=0.05)
    assert np.percentile(ratio, 99.9) < RESIDUAL_SIGMAS  # a right pose is not flagged for its noise
    assert np.mean(out.flags & HIGH_RESIDUAL != 0) < 1e-3


def test_the_gate_widens_with_the_tables_model_error_and_still_flags_a_wrong_signal(exact_table, rng):
    """A table 4 % off the room's field (a strong room's model error) leaves residuals over the fixed 1e-3 at many
    right poses; recording the table's measured model error (its pose-equivalent RMS, as the cross-validation
    measures it) in the fit record makes them trusted, and a signal no pose explains is still flagged."""
    r = ball(rng, 3000, 0.18)
    T = rotations.to_matrix(rotations.random(len(r), rng))
    S = dipole.signal(r, T, quadratic_field(r)) + 1e-4 * rng.standard_normal((len(r), 3, 3))
    off = replace(exact_table, values=1.04 * exact_table.values)  # the model's error: 4 % of the secondary field
    nodes = ball(rng, 20000, 0.18)
    error = leverage(nodes) * np.linalg.norm(0.04 * quadratic_field(nodes), axis=(1, 2))
    cv_mm = 1000 * float(np.sqrt(np.mean(error**2)))  # what a perfect cross-validation of this table measures

    fixed = Corrector(_with_record(off, sigma=1e-4)).batch(S)  # no model error recorded: the fixed limit
    assert Corrector(_with_record(off, sigma=1e-4)).residual_gate.fixed == MAX_RESIDUAL
    assert np.mean(fixed.flags & HIGH_RESIDUAL != 0) > 0.2  # flagged because the room is strong
    scaled_corrector = Corrector(_with_record(off, cv_mm=cv_mm, sigma=1e-4))
    scaled = scaled_corrector.batch(S)
    assert scaled_corrector.residual_gate.scaled
    assert np.mean(scaled.flags & HIGH_RESIDUAL != 0) < 1e-3
    np.testing.assert_allclose(scaled.position, fixed.position)  # the same poses, only the flag differs

    # the limit is proportional to the model error where it dominates the noise
    half = Corrector(_with_record(off, cv_mm=cv_mm / 2, sigma=1e-9)).residual_gate
    full = Corrector(_with_record(off, cv_mm=cv_mm, sigma=1e-9)).residual_gate
    np.testing.assert_allclose(full.limits(S, r), 2 * half.limits(S, r), rtol=1e-6)

    # a wrong signal (a room that changed, another hemisphere's branch) stands out against the widened limit
    kicked = S[:50] + 0.15 * np.abs(S[:50]).max(axis=(1, 2))[:, None, None] * np.array(
        [[1, -1, 0], [0, 1, 1], [1, 0, -1.0]])
    assert np.all(scaled_corrector.batch(kicked).flags & HIGH_RESIDUAL)


def test_an_explicit_limit_overrides_and_a_table_without_a_record_keeps_the_fixed_limit(exact_table):
    table = _with_record(exact_table, cv_mm=0.05, sigma=1e-3)
    assert Corrector(table, max_residual=2e-3).residual_gate.fixed == 2e-3
    assert Corrector(table).residual_gate.fixed is None
    for record in ({}, {"cv_mm": 0.05}, {"sigma": 1e-3}):
        gate = Corrector(_with_record(exact_table, **record)).residual_gate
        assert gate.fixed == MAX_RESIDUAL and "records no" in gate.describe()
    with pytest.raises(InputError, match="max_residual"):
        ResidualGate.resolve(table, max_residual=-1.0)
