"""The typed fit report (ivc.table.fit_report): the same fields from every fit path, the stored record kept."""

import json

import pytest

from ivc import lut
from ivc.cli.fit import render_fit
from ivc.errors import LutError
from ivc.lut import FitOptions, HarmonicFit
from ivc.table import FitReport


@pytest.mark.parametrize("options", [FitOptions(fitter=HarmonicFit(), min_support=5, refine=True, max_refinements=1),
                                     FitOptions(fitter=HarmonicFit(degree=4), min_support=5, refine=False)],
                         ids=["refined", "fixed-degree"])
def test_a_single_sweep_fit_reports_typed_fields(small_session, options, tmp_path):
    _, session = small_session
    table = lut.fit_lut(session, options)
    report, fit = table.report, table.fit
    assert report.input == "signals" and report.reported_poses is None and report.method == fit["method"]
    assert (report.frames.recorded, report.frames.used, report.frames.stride) == (
        fit["frames"]["recorded"], fit["frames"]["used"], fit["frames"]["stride"])
    assert report.samples.kept == fit["samples"]["kept"] <= report.samples.total
    assert report.samples.dropped == fit["samples"]["dropped"] and report.samples.anchor is None
    assert report.degree == fit["degree"] and report.sources is None and report.cv_rms_mm == fit["cv_rms_mm"]
    assert [step.cv_rms_mm for step in report.refinement] == [step["cv_rms_mm"] for step in fit["refinement"]]
    assert len(report.refinement) == (1 if options.refine else 0) and report.rounds == ()
    assert report.signal_noise == fit["signal_noise"] and report.valid_nodes == int(table.valid.sum())
    assert report.model_text().startswith(f"degree {fit['degree']} (")
    # the record as stored, key for key, through the table file
    assert report.to_dict() == fit
    lut.write(table, tmp_path / "t.h5")
    again = lut.read(tmp_path / "t.h5")
    assert again.report == report and json.dumps(again.report.to_dict()) == json.dumps(fit)
    assert f"Fit: {fit['method']}, {report.model_text()}" in render_fit(table)


def test_a_record_without_the_fit_fields_is_a_clear_error(exact_table):
    with pytest.raises(LutError, match="fit record is incomplete"):
        _ = exact_table.report


def test_equivalent_sources_and_joint_rounds_read_typed():
    fit = {"method": "equivalent sources, joint", "sources": 120, "damping": 1e-6, "damping_chosen_by": "given",
           "cv_rms_mm": None, "cv_folds": 5,
           "rounds": [{"iteration": 0, "samples": 10, "mapped_litres": 1.5, "map_change_mm": None,
                       "frames_solved": {"extension_sweep_1": 0}}],
           "never_touched_mapped_region": ["extension_sweep_2"], "error_by_distance": [],
           "frames": {"recorded": 8, "used": 4, "stride": 2},
           "samples": {"total": 10, "kept": 10, "used": 10, "anchor": 6, "outside_grid": 0, "dropped": {}},
           "refinement": [], "grid_from": "data (one-cell margin)", "min_support": 5, "valid_nodes": 3}
    report = FitReport.from_dict(fit)
    assert report.model_text() == "120 dipoles, damping 1e-06 (given)" and report.degree is None
    assert report.rounds[0].frames_solved == {"extension_sweep_1": 0} and report.rounds[0].map_change_mm is None
    assert report.samples.anchor == 6 and report.never_touched_mapped_region == ("extension_sweep_2",)
    assert report.to_dict() == fit and report.to_dict() is not report.stored
