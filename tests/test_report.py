"""``ivc report``: built from the demo session with every figure, and honest without truth."""

import base64
import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from matplotlib.image import imread

from ivc import demo as ivc_demo
from ivc import dipole, lut
from ivc import session as session_io
from ivc.cli import cli
from ivc.correct.evaluate import evaluate
from ivc.fixtures.mapping import FixtureModel
from ivc.lut import Grid
from ivc.report import FIGURES, build_report
from ivc.report.compute import cell_counts, declared_cube, mapped_layers, percent_of_measured
from ivc.report.figures import mapped_boundary
from ivc.session import Session


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A small demo run (what `ivc demo --keep` writes): the session and its table."""
    result = ivc_demo.run(sweep_frames=3000, check_frames=300, folder=tmp_path_factory.mktemp("demo"))
    return result.session_file, result.table_file


@pytest.fixture(scope="module")
def demo_report(demo, tmp_path_factory):
    """`ivc report` of the demo session and table: its folder and the command's result (built once, read by
    the tests that need the whole session's report)."""
    session_file, lut_file = demo
    out = tmp_path_factory.mktemp("demo-report") / "report"
    result = CliRunner().invoke(cli, ["report", str(session_file), str(lut_file), "-o", str(out), "--quiet"])
    return out, result


class _Images(HTMLParser):
    def __init__(self):
        super().__init__()
        self.sources, self.figures = [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.sources.append(attrs["src"])
        if tag == "figure":
            self.figures.append(attrs["id"])


def _embedded(page: str) -> dict[str, bytes]:
    parser = _Images()
    parser.feed(page)
    prefix = "data:image/png;base64,"
    assert all(src.startswith(prefix) for src in parser.sources), "every image is embedded, none linked"
    return {f.removeprefix("fig-"): base64.b64decode(s[len(prefix):])
            for f, s in zip(parser.figures, parser.sources, strict=True)}


@pytest.mark.slow
def test_report_builds_from_the_demo_session_with_every_figure(demo, demo_report):
    session_file, lut_file = demo
    out, result = demo_report
    assert result.exit_code == 0, result.output
    page = (out / "report.html").read_text()
    embedded = _embedded(page)
    assert set(embedded) == set(FIGURES)
    for name in FIGURES:
        png = (out / f"{name}.png").read_bytes()
        assert embedded[name] == png, f"{name}: the page embeds the PNG that was written"
        image = imread(out / f"{name}.png")
        assert image.shape[0] > 300 and image.shape[1] > 600
        assert image[..., :3].std() > 0.05, f"{name} is blank"
    assert "Not drawn" not in page

    numbers = json.loads((out / "report.json").read_text())
    table, session = lut.read(lut_file), session_io.read(session_file)
    expected = evaluate(table, session)
    check = numbers["check"]
    assert check["corrected"] == expected["corrected"]
    assert check["ivc"]["position_mm"] == pytest.approx(expected["ivc"]["position_mm"], abs=1e-4)
    assert check["dipole"]["orientation_mrad"] == pytest.approx(expected["dipole"]["orientation_mrad"], abs=1e-4)
    # the report solves the sweep again with the fit's gates: the same samples survive
    assert numbers["sweep"]["samples"]["kept"] == table.fit["samples"]["kept"]
    assert numbers["table"]["valid_nodes"] == int(table.valid.sum())
    assert numbers["sweep"]["sensor0_position_mm"]["p50"] < 1.0  # truth is there, so errors are reported

    again = CliRunner().invoke(cli, ["report", str(session_file), str(lut_file), "-o", str(out), "--quiet"])
    assert again.exit_code != 0 and "--force" in again.output
    assert (out / "report.html").read_text() == page, "a refused run changes nothing"


@pytest.mark.slow
def test_report_without_truth_says_what_it_cannot_draw(demo, tmp_path):
    session_file, lut_file = demo
    full = session_io.read(session_file)
    session = Session(full.hemisphere, full.steps, {}, full.attrs)
    report = build_report(session, lut.read(lut_file), tmp_path)
    assert set(report.missing) == {"error_histograms"}
    assert "truth" in report.missing["error_histograms"]
    page = report.html.read_text()
    assert set(_embedded(page)) == set(FIGURES) - {"error_histograms"}
    assert "Not drawn" in page and "truth" in page
    assert "sensor0_position_mm" not in report.numbers["sweep"]
    assert "missing" in report.numbers["check"]


@pytest.mark.slow
def test_a_check_file_without_the_step_is_named(demo, tmp_path):
    session_file, lut_file = demo
    full = session_io.read(session_file)
    other = Session(full.hemisphere, {"cube_survey": full.steps["cube_survey"]}, {}, full.attrs)
    check_file = tmp_path / "other.h5"
    session_io.write(other, check_file)
    result = CliRunner().invoke(cli, ["report", str(session_file), str(lut_file), str(check_file), "-o",
                                      str(tmp_path / "r"), "--quiet"])
    assert result.exit_code == 0, result.output
    assert f"{check_file} has no 'check' step" in result.output


@pytest.mark.slow
def test_a_session_without_its_sweep_reports_the_table_and_check_poses_only(demo, demo_report, tmp_path):
    session_file, lut_file = demo
    full = session_io.read(session_file)
    steps = {name: step for name, step in full.steps.items() if name not in ("wand_sweep", "wand_calibration")}
    partial = tmp_path / "no_sweep.h5"
    truth = {name: t for name, t in full.truth.items() if name in steps}
    session_io.write(Session(full.hemisphere, steps, truth, full.attrs), partial)
    out = tmp_path / "r"
    result = CliRunner().invoke(cli, ["report", str(partial), str(lut_file), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    assert "no wand_calibration step and no wand_sweep step" in result.output
    assert "not drawn: lambda_vs_error, cube_residuals, coverage" in result.output

    page = (out / "report.html").read_text()
    drawn = {"secondary_field", "error_histograms", "error_vs_distance"}
    assert set(_embedded(page)) == drawn
    assert {p.name for p in out.iterdir()} == {"report.html", "report.json", *(f"{n}.png" for n in drawn)}
    numbers = json.loads((out / "report.json").read_text())
    assert set(numbers["figures_missing"]) == set(FIGURES) - drawn
    expected = evaluate(lut.read(lut_file), full)
    assert numbers["check"]["ivc"]["position_mm"] == pytest.approx(expected["ivc"]["position_mm"], abs=1e-4)
    assert numbers["sweep"]["missing"] == ["no wand_calibration step", "no wand_sweep step"]
    # distances run from the ideal cube at the declared pose: eq. 87 with the ideal vertices, a few mm
    # from the calibrated cube (the simulated cube is built off-true, as Himberg 2010's was)
    ideal = FixtureModel.from_session(full, "ideal").placement.positions
    np.testing.assert_allclose(declared_cube(full), ideal, atol=1e-12)
    assert numbers["cube"]["centre_mm"] == pytest.approx(1000 * ideal.mean(axis=0), abs=1e-3)
    assert numbers["cube"]["vertices"] == "the ideal cube at the declared pose"
    whole_out, whole_result = demo_report  # the whole session's report, as `ivc report` wrote it
    assert whole_result.exit_code == 0, whole_result.output
    whole = json.loads((whole_out / "report.json").read_text())
    assert numbers["check"]["distance_from_cube_mm"]["p50"] == pytest.approx(
        whole["check"]["distance_from_cube_mm"]["p50"], abs=5.0)


@pytest.mark.slow
def test_a_check_recording_without_a_cube_gets_no_distances(demo, tmp_path):
    session_file, lut_file = demo
    full = session_io.read(session_file)
    alone = Session(full.hemisphere, {"check": full.steps["check"]}, {"check": full.truth["check"]}, full.attrs)
    report = build_report(alone, lut.read(lut_file), tmp_path)
    assert "error_histograms" not in report.missing
    assert "no cube to measure distances from" in report.missing["error_vs_distance"]
    assert "distance_from_cube_mm" not in report.numbers["check"]
    assert "centre_mm" not in report.numbers["cube"]
    assert "Not drawn" in report.html.read_text()


def test_percent_of_the_measured_signal():
    r = np.array([[0.4, 0.1, -0.2], [0.7, -0.3, 0.1]])
    f = dipole.field(r)
    assert percent_of_measured(f, r) == pytest.approx([50.0, 50.0])  # G = f_D: half of what is measured
    assert percent_of_measured(np.zeros_like(f), r) == pytest.approx([0.0, 0.0])
    assert percent_of_measured(-0.5 * f, r) == pytest.approx([100.0, 100.0])


def test_cell_counts_hold_every_sample_inside_the_grid(rng):
    grid = Grid(np.array([0.2, -0.1, -0.1]), 0.05, (5, 4, 6))
    positions = rng.uniform([0.15, -0.15, -0.15], [0.45, 0.1, 0.2], (5000, 3))
    from ivc.table.lookup import LookupTable

    table = LookupTable(grid, np.zeros((*grid.shape, 3, 3)), np.ones(grid.shape, bool), np.zeros(grid.shape))
    counts = cell_counts(table, positions)
    assert counts.shape == (4, 3, 5)
    assert counts.sum() == grid.contains(positions).sum()
    cell = np.floor((positions[0] - grid.origin) / grid.spacing).astype(int)
    inside = np.all(np.floor((positions - grid.origin) / grid.spacing).astype(int) == cell, axis=1)
    if grid.contains(positions[:1])[0]:
        assert counts[tuple(cell)] == inside.sum()


def test_mapped_volume_outline_and_slice_choice():
    X, Y = np.arange(4.0), np.arange(4.0)
    single = np.zeros((3, 3), bool)
    single[1, 1] = True
    assert len(mapped_boundary(single, X, Y)) == 4
    ell = single.copy()
    ell[1, 2] = ell[2, 1] = True  # three cells in an L: 8 edges on its outline
    assert len(mapped_boundary(ell, X, Y)) == 8
    cells = np.zeros((2, 2, 20), bool)
    cells[:, :, 3:17] = True
    layers = mapped_layers(cells, keep=9)
    assert len(layers) == 6 and 9 in layers and layers[0] == 3 and layers[-1] == 16


SAMPLES = Path(__file__).resolve().parents[1] / "sample_data" / "recordings"


@pytest.fixture(scope="module")
def sample_report(tmp_path_factory):
    """A report of the sample data's check poses (three figures): the folder and a copy of every file's bytes."""
    out = tmp_path_factory.mktemp("sample-report")
    build_report(session_io.read(SAMPLES / "default_room_check.h5"), lut.read(SAMPLES / "default_room_lut.h5"),
                 out)
    return out, {path.name: path.read_bytes() for path in out.iterdir()}


@pytest.mark.parametrize("fail_at", ["drawing", "writing", "swapping"])
def test_an_interrupted_report_leaves_the_old_one_whole(sample_report, monkeypatch, fail_at):
    import ivc.report as report_module

    out, before = sample_report
    (out / "notes.txt").write_text("mine")  # a file of the user's in the same folder is never touched
    calls = {"n": 0}

    def interrupt_on_second(real):
        def wrapped(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
            return real(*args, **kwargs)
        return wrapped

    if fail_at == "drawing":
        monkeypatch.setattr(report_module, "_png", interrupt_on_second(report_module._png))
    elif fail_at == "writing":  # a full disk while the new files are written
        real_write = Path.write_bytes

        def full_disk(self, data):
            calls["n"] += 1
            if calls["n"] == 2:
                raise OSError(28, "No space left on device")
            return real_write(self, data)
        monkeypatch.setattr(Path, "write_bytes", full_disk)
    else:  # between moving the old files aside and the new ones in
        monkeypatch.setattr(report_module.os, "replace", interrupt_on_second(report_module.os.replace))
    with pytest.raises((KeyboardInterrupt, OSError)):
        build_report(session_io.read(SAMPLES / "default_room_check.h5"),
                     lut.read(SAMPLES / "default_room_lut.h5"), out, overwrite=True)
    monkeypatch.undo()
    after = {path.name: path.read_bytes() for path in out.iterdir()}
    assert after.pop("notes.txt") == b"mine"
    assert after == before, "the old report is whole, with no new or hidden file beside it"


def test_a_report_into_a_folder_it_cannot_write_is_refused_before_the_work(tmp_path):
    blocker = tmp_path / "results"
    blocker.write_text("a file where the report's parent folder should be")
    with pytest.raises(PermissionError, match="not a writable folder"):
        build_report(Session(), None, blocker / "report")  # refused before the session is even looked at
    assert blocker.read_text().startswith("a file")
