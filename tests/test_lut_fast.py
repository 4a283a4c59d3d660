"""The fast paths of the harmonic fit and the refinement's stopping rule, against their plain forms."""

import numpy as np

from ivc.lut import FitOptions, fit_lut, harmonics
from ivc.lut import fit_harmonic as fh
from ivc.lut.samples import FieldSamples
from tests.helpers import ball, quadratic_field, samples_of


def test_compiled_gradient_rows_equal_the_numpy_basis(rng):
    x = 0.6 * rng.standard_normal((300, 3))
    for degree in (1, 2, 3, 7, 10):
        want = harmonics.gradients(x, degree).transpose(0, 2, 1)
        np.testing.assert_allclose(harmonics.gradient_rows(x, degree), want, rtol=1e-13, atol=1e-15)


def _normal_direct(samples, weights, fold, k, centre, scale, degree):
    """The fold normal equations summed sample by sample, with the plain NumPy basis."""
    K = harmonics.count(degree)
    basis = harmonics.gradients((samples.positions - centre) / scale, degree)  # (n, K, 3)
    gram, rhs, yy, count = np.zeros((k, K, K)), np.zeros((k, K, 3)), np.zeros(k), np.zeros(k)
    lever = samples.leverage()
    for f in range(k):
        m = fold == f
        X = (basis[m] * np.sqrt(weights[m])[:, None, None]).transpose(0, 2, 1).reshape(-1, K)
        Y = (samples.fields[m] * np.sqrt(weights[m])[:, None, None]).reshape(-1, 3)
        gram[f], rhs[f], yy[f] = X.T @ X, X.T @ Y, np.sum(Y**2)
        count[f] = np.sum(weights[m] / lever[m] ** 2)
    return gram, rhs, yy, count


def test_huber_reweighting_by_downdates_equals_a_full_pass(rng):
    samples = samples_of(quadratic_field, ball(rng, 3000, 0.2))
    samples.fields[::40] *= 1.5  # outliers
    centre, scale, degree, k = samples.positions.mean(axis=0), 0.2, 4, 5
    fold, base, lever = samples.folds(k, block_frames=100), samples.weights(), samples.leverage()
    unweighted = fh.accumulate_normal(samples, lever, base, fold, k, centre, scale, degree, None)
    for got, want in zip((unweighted.gram, unweighted.rhs, unweighted.yy, unweighted.count),
                         _normal_direct(samples, base, fold, k, centre, scale, degree), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-12 * np.abs(want).max())
    coefficients = fh.solve_normal(unweighted.gram.sum(axis=0)[:8, :8], unweighted.rhs.sum(axis=0)[:8])  # degree 2
    rows = harmonics.gradient_rows((samples.positions - centre) / scale, 2)
    residual = fh.standardised_residual(samples, lever, np.arange(len(samples)), rows, coefficients)
    cut = 2.0 * np.median(residual)
    normal, weights = fh.reweight_normal(unweighted, samples, lever, base, fold, k, centre, scale, degree, coefficients,
                                         cut,
                                   None)
    np.testing.assert_allclose(weights, base * np.minimum(1.0, cut / residual), rtol=1e-12)
    assert np.sum(weights < base) > 0.2 * len(samples)
    for got, want in zip((normal.gram, normal.rhs, normal.yy, normal.count),
                         _normal_direct(samples, weights, fold, k, centre, scale, degree), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10 * np.abs(want).max())


def test_refinement_keeps_the_best_map_and_says_why_it_stopped(small_session):
    _, session = small_session
    table = fit_lut(session, FitOptions(refine=True, max_refinements=3, min_support=5))
    history, fit = table.fit["refinement"], table.fit
    assert 1 <= len(history) <= 3 and sum(step["kept"] for step in history) <= 1
    scores = [step["cv_rms_mm"] for step in history]
    kept = [step["cv_rms_mm"] for step in history if step["kept"]]
    # the kept map is the best-scoring one (the first fit's when no refinement beat it)
    assert fit["cv_rms_mm"] == (kept[0] if kept else fit["cv_rms_mm"]) and fit["cv_rms_mm"] <= min(scores)
    assert fit["refinement_stopped"]
    if len(history) < 3:
        assert "less than" in fit["refinement_stopped"]


def test_field_samples_roundtrip_through_the_fit_unchanged(rng):
    # the fit reads samples only: positions and fields are not modified in place
    samples = samples_of(quadratic_field, ball(rng, 2000, 0.2))
    before = FieldSamples(samples.positions.copy(), samples.fields.copy(), samples.error.copy(), samples.frame.copy(),
                          samples.sensor.copy())
    fh.fit_harmonic(samples, degree=3)
    np.testing.assert_array_equal(samples.positions, before.positions)
    np.testing.assert_array_equal(samples.fields, before.fields)


def test_compiled_rigid_solve_equals_numpy(small_session):
    from ivc.fixtures.mapping import FixtureModel, Gates, map_sweep
    from ivc.lut.refine import solve_rigid

    _, session = small_session
    table = fit_lut(session, FitOptions(min_support=5, refine=False))
    model = FixtureModel.from_session(session)
    part = session.select_frames("wand_sweep", slice(0, 600))
    mapping = map_sweep(part, model, Gates())
    sweep = part.steps["wand_sweep"]
    args = (sweep.signal_matrices(), sweep.valid_mask, model.wand, model.interpolant.value_and_jacobian, table.field(),
            mapping.positions[:, 0], mapping.rotations[:, 0])
    r, T, ok = solve_rigid(*args)
    r_ref, T_ref, ok_ref = solve_rigid(*args, compiled=False)
    assert ok.mean() > 0.95
    np.testing.assert_array_equal(ok, ok_ref)
    np.testing.assert_allclose(r[ok], r_ref[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(T[ok], T_ref[ok], rtol=0, atol=1e-9)
