"""The LUT fitters as estimators: one interface, one blocked cross-validation, fit_lut built on them."""

import numpy as np
import pytest

from ivc.errors import InputError
from ivc.fixtures.mapping import FixtureModel, Gates, map_sweep
from ivc.lut import (
    BlockedKFold,
    FitOptions,
    Fitter,
    Grid,
    GridField,
    HarmonicFit,
    PolyFit,
    cross_validate,
    fit_lut,
    fit_table,
    held_out_score,
    make_fitter,
)
from ivc.lut.fit_harmonic import fit_harmonic
from ivc.lut.fit_poly import fit_poly
from ivc.lut.samples import ERROR_FLOOR, FieldSamples
from tests.helpers import ball, quadratic_field, samples_of


def _quiet_samples(rng, n=6000):
    """A degree-3 field plus noise bounded at 0.3 of each sample's error (standardised), so that no sample
    is an outlier to the Huber rounds and every fit weighs the samples alike."""
    samples = samples_of(quadratic_field, ball(rng, n, 0.2))
    sigma = np.sqrt(samples.error**2 + ERROR_FLOOR**2) / samples.leverage()
    samples.fields += 0.1 * rng.uniform(-1, 1, samples.fields.shape) * sigma[:, None, None]
    samples.frame = np.arange(n)  # one sample a frame: blocks of 500 frames
    return samples


def test_harmonic_fit_is_an_estimator(rng):
    samples = _quiet_samples(rng)
    fitter = HarmonicFit(degree=3)
    assert fitter.fit(samples) is fitter and fitter.degree_ == 3 and fitter.report_["degree_chosen_by"] == "user"
    model, report = fit_harmonic(samples, degree=3)
    r = ball(rng, 50, 0.15)
    np.testing.assert_array_equal(fitter.predict(r), model(r))
    assert report == fitter.report_ and fitter.cv_score_ == pytest.approx(report["cv_rms_mm"] / 1000, rel=1e-15)
    copy = fitter.clone()
    assert copy.get_params() == fitter.get_params() and not hasattr(copy, "model_")
    with pytest.raises(InputError, match="not fitted"):
        copy.predict(r)


def test_the_harmonic_shortcut_equals_refitting_without_each_fold(rng):
    # the exact held-out residuals of the fold normal equations against the generic blocked CV
    # (a copy fitted per fold): equal to round-off when no sample is down-weighted
    samples = _quiet_samples(rng)
    fitter = HarmonicFit(degree=3).fit(samples)
    assert fitter.report_["outliers_downweighted"] == 0
    grid = Grid.around(samples.positions, 0.0381)
    generic = cross_validate(fitter, samples, grid)
    assert fitter.cross_validate(samples, grid) == fitter.cv_score_
    assert generic == pytest.approx(fitter.cv_score_, rel=1e-9)
    # the CV's folds are blocks of 500 consecutive frames
    fold = BlockedKFold().folds(samples)
    assert np.array_equal(fold, (samples.frame // 500) % 5)


def test_poly_fit_is_an_estimator_and_its_score_is_the_blocked_cv(rng):
    samples = samples_of(quadratic_field, ball(rng, 20_000, 0.2))
    samples.frame = np.arange(len(samples)) // 4
    grid = Grid.around(samples.positions, 0.0381)
    fitter = PolyFit()
    values, report = fit_table(fitter, samples, grid)
    np.testing.assert_array_equal(values, fit_poly(samples, grid, 2, grid.spacing))
    assert report["degree"] == 2 and report["degree_chosen_by"] == "default" and report["cv_folds"] == 5
    # the score, written out: each fold's samples against the grid fitted without them, interpolated
    fold = (samples.frame // 500) % 5
    predicted = np.full_like(samples.fields, np.nan)
    for f in range(5):
        held = fold == f
        part = fit_poly(samples.subset(~held), grid, 2, grid.spacing)
        g, _, mapped = GridField(grid, part, np.ones(grid.shape, bool)).evaluate(samples.positions[held])
        g[~mapped] = np.nan
        predicted[held] = g
    precision = samples.weights() / samples.leverage() ** 2
    lever = samples.leverage()
    residual = lever * np.linalg.norm(predicted - samples.fields, axis=(1, 2))
    ok = np.isfinite(residual)
    want = np.sqrt(np.sum(precision[ok] * residual[ok] ** 2) / np.sum(precision[ok]))
    assert report["cv_rms_mm"] == pytest.approx(1000 * want, rel=1e-12)
    assert held_out_score(samples, predicted) == pytest.approx(want, rel=1e-12)
    with pytest.raises(InputError, match="fit\\(samples, grid\\)"):
        PolyFit().fit(samples)


def test_fitters_refuse_bad_configurations():
    with pytest.raises(InputError, match="unknown fit method 'spline'"):
        FitOptions(fitter="spline")
    with pytest.raises(InputError, match="harmonic degree"):
        HarmonicFit(degree=0)
    with pytest.raises(InputError, match="radius"):
        PolyFit(radius=-1.0)
    with pytest.raises(InputError, match="cross-validation k"):
        BlockedKFold(k=1)
    assert isinstance(make_fitter("poly", degree=3), PolyFit) and FitOptions().method == "harmonic"


class MeanField(Fitter):
    """A third fitter in a dozen lines: the weighted mean of the samples' fields, everywhere."""

    name = "mean"

    def __init__(self, cv: BlockedKFold | None = None):
        self.cv = BlockedKFold() if cv is None else cv

    def fit(self, samples: FieldSamples, grid=None, progress=None):
        w = samples.weights()
        self.mean_ = np.tensordot(w, samples.fields, axes=1) / w.sum()
        self.report_ = {"degree": 0, "degree_chosen_by": "user"}
        return self

    def predict(self, positions):
        return np.broadcast_to(self.mean_, np.shape(positions)[:-1] + (3, 3)).copy()


def _samples_of_session(session):
    model = FixtureModel.from_session(session)
    return FieldSamples.from_mapping(map_sweep(session, model, Gates()))


def test_fit_lut_is_the_fitters_applied_to_the_gated_samples(small_session):
    # behaviour unchanged: the table and its score are what the estimators give the sweep's samples
    # (bit-identical; the estimators themselves are checked against their plain forms above). The small
    # sweep is too thin for the poly fit's cross-validation; a third fitter goes through unchanged
    _, session = small_session
    samples = _samples_of_session(session)
    grid = Grid.around(samples.positions, 0.0381)
    for fitter in (HarmonicFit(), HarmonicFit(degree=4, cv=BlockedKFold(4, 250)), MeanField()):
        options = FitOptions(fitter=fitter, min_support=5, refine=False)
        table = fit_lut(session, options)
        values, report = fit_table(fitter.clone(), samples, grid)
        np.testing.assert_array_equal(table.values, values)
        assert table.fit["method"] == fitter.name and table.fit["cv_rms_mm"] == report["cv_rms_mm"]
        assert table.provenance["parameters"]["method"] == fitter.name
        assert not hasattr(options.fitter, "report_")  # the options' fitter is copied, not fitted in place
    assert table.fit["cv_rms_mm"] > 10 * fit_lut(session, FitOptions(min_support=5, refine=False)).fit["cv_rms_mm"]
