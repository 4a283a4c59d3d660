"""The qualitative outcomes of docs/math.md §14.4 on synthetic head motion (fixed seeds), at the thesis's 50 ms."""

import numpy as np
import pytest

from ivc.predict import make
from ivc.predict.motion import head_motion
from ivc.predict.studies.evaluate import HORIZONS_MS, error_table, evaluate, plot_error_vs_horizon, snr_table

#: slow (four synthetic motions through every predictor); deselected by -m "not slow"
pytestmark = pytest.mark.slow

NAMES = ("none", "dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3", "q-ekf")


@pytest.fixture(scope="module")
def results():
    out = {}
    for motion in ("benign", "moderate", "aggressive", "full"):
        h = head_motion(motion, 8000, seed=11)
        for name in NAMES:
            out[motion, name] = evaluate(make(name), h.measured, 120.0, motion, omega_true=h.omega)
    return out


def mean50(results, motion, name):
    return results[motion, name].at(50.0)["mean"]


def test_every_predictor_beats_no_prediction_on_moderate_and_aggressive(results):
    for motion in ("moderate", "aggressive"):
        for name in NAMES[1:]:
            assert mean50(results, motion, name) < 0.5 * mean50(results, motion, "none"), (motion, name)


def test_benign_motion_cv_filters_are_close_to_no_prediction(results):
    for name in ("dqekf-cv", "mmdq2", "mmdq3", "q-ekf"):
        assert mean50(results, "benign", name) < 2.0 * mean50(results, "benign", "none")


def test_dq_beats_q_on_aggressive_and_full_range(results):
    for motion in ("aggressive", "full"):
        assert mean50(results, motion, "dqekf-cv") < mean50(results, motion, "q-ekf")


def test_cv_is_worst_on_aggressive_and_mmdq2_cuts_its_peaks(results):
    """The thesis also finds MMDQ2's peak the lowest of all; here DQ-EKF CA's is as low or lower.

    That is reported by the benchmark, not asserted.
    """
    errors = {n: mean50(results, "aggressive", n) for n in NAMES[1:5]}
    assert max(errors, key=errors.get) == "dqekf-cv"
    peaks = {n: results["aggressive", n].at(50.0)["max"] for n in NAMES[1:5]}
    assert peaks["mmdq2"] < peaks["dqekf-cv"] / 2
    assert mean50(results, "aggressive", "mmdq2") < mean50(results, "aggressive", "dqekf-cv") / 2
    # MMDQ2 ≈ MMDQ3, and CA ≈ MMDQ in median error
    assert mean50(results, "aggressive", "mmdq3") == pytest.approx(mean50(results, "aggressive", "mmdq2"), rel=0.25)
    ca, mm = (results["aggressive", n].at(50.0)["median"] for n in ("dqekf-ca", "mmdq2"))
    assert 0.5 < ca / mm < 2.0


def test_snr_falls_with_horizon_and_error_grows(results):
    for name in ("dqekf-cv", "mmdq2"):
        rows = results["moderate", name].rows
        assert rows[0]["snr_db"] - rows[-1]["snr_db"] > 3.0
        means = [r["mean"] for r in rows]
        assert np.all(np.diff(means[1:]) > 0)
    assert results["moderate", "none"].rows[0]["mean"] < 1e-9
    assert len(results["moderate", "none"].rows) == len(HORIZONS_MS)


def test_snr_table_prints_the_evaluated_snr(results):
    chosen = [results["moderate", n] for n in ("none", "dqekf-cv")]
    lines = snr_table(chosen, (0.0, 50.0)).splitlines()
    row = next(line for line in lines if line.startswith("dqekf-cv"))
    assert row.split()[1:] == [f"{chosen[1].at(h)['snr_db']:.1f}" for h in (0.0, 50.0)]


def test_tables_name_each_motion_in_full_over_its_columns(results):
    chosen = [results[m, n] for m in ("moderate", "aggressive") for n in ("none", "mmdq2")]
    for table in (error_table(chosen), snr_table(chosen, (0.0, 50.0))):
        group, columns, first = table.splitlines()[1:4]
        assert group.split() == ["moderate", "aggressive"]
        assert first.startswith("none") and len(first) == len(columns)  # cells sit under their headers
        middle = len(columns.rstrip()) // 2  # the second motion's group starts halfway along
        assert group.index("aggressive") > middle > group.index("moderate")
    row = next(line for line in error_table(chosen).splitlines() if line.startswith("mmdq2"))
    assert row.split()[4] == f"{results['aggressive', 'mmdq2'].at(50.0)['mean']:.2f}"


def test_velocity_error_is_reported_for_rate_estimators(results):
    v = results["moderate", "dqekf-cv"].velocity
    assert v is not None and 0 < v["median"] < 100  # mrad/s
    assert results["moderate", "none"].velocity is None


def test_error_vs_horizon_plot(results, tmp_path):
    path = tmp_path / "horizon.png"
    plot_error_vs_horizon(list(results.values()), path)
    assert path.stat().st_size > 10_000
