"""Readers for other programs' recordings: head-orientation traces and Polhemus Liberty logger CSVs."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from ivc import rotations
from ivc.collect import read_recording, replay, sniff
from ivc.errors import CsvError

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
HEAD = DATA / "head_motion" / "user1_quaternion.txt"
LIBERTY = DATA / "polhemus_liberty"


def _trace(path: Path, rows: list[str]) -> Path:
    path.write_text("timestamp viewpoint w x y z\n" + "\n".join(rows) + "\n")
    return path


def test_head_trace_quirks_are_reported(tmp_path):
    q = rotations.from_rotvec(np.array([[0.0, 0.0, 0.01 * k] for k in range(6)]))
    signs = [1, -1, 1, 1, -1, 1]
    rows = [f"{0.017 * k} 0 " + " ".join(repr(float(v)) for v in signs[k] * q[k]) for k in range(6)]
    rows.insert(3, rows[2])  # an exact repeat of a row: same time
    rows.append(f"{0.017 * 7} 1 " + " ".join(repr(float(v)) for v in q[5]))  # same orientation, later
    path = _trace(tmp_path / "t.txt", rows)
    assert sniff(path) == "head-trace"
    step, report = read_recording(path)
    assert step.n_frames == 7 and step.n_sensors == 1
    text = report.text()
    assert "dropped 1 rows repeating the previous row's time (first at line 5)" in text
    assert "sign continuous" in text and "1 samples repeat the previous orientation" in text
    assert np.all(np.sum(step.quaternion[1:, 0] * step.quaternion[:-1, 0], axis=1) > 0)
    assert np.allclose(rotations.angle_between(step.quaternion[:6, 0], q), 0.0, atol=1e-12)
    assert step.attrs["orientation_only"] and step.attrs["import_report"] == text
    assert step.sample_rate_hz == pytest.approx(1 / 0.017, rel=1e-4)
    assert replay(path, "check")[0].n_frames == 7


def test_head_trace_bad_rows_refused(tmp_path):
    path = _trace(tmp_path / "t.txt", ["0 0 1 0 0 0", "0.1 0 0.5 0 0 0", "0.2 0 x 0 0 0"])
    with pytest.raises(CsvError, match=r"line 3: the quaternion has norm 0\.5(.|\n)*line 4"):
        read_recording(path)


def _liberty(path: Path, frames: int, dropout: slice | None = None) -> tuple[Path, np.ndarray]:
    """A logger file as the Liberty's: each frame written 3 times, sensor 1 on one row, sensor 2 on the next."""
    t = np.arange(frames) / 120.0
    q1 = rotations.from_rotvec(np.c_[0.001 * np.sin(t), np.zeros(frames), np.zeros(frames)])
    q2 = rotations.from_rotvec(np.c_[np.zeros(frames), 0.5 * t, np.zeros(frames)])
    p1 = np.tile([20.0, 5.0, 3.0], (frames, 1))
    p2 = np.c_[30.0 + t, -2.0 + 0 * t, 4.0 + 0 * t]
    if dropout is not None:
        p2[dropout] = [0.01, -0.02, 0.0]
    lines = ["Time,w1,x1,y1,z1,w2,x2,y2,z2,loc1_x,loc1_y,loc1_z,loc2_x,loc2_y,loc2_z"]
    state = [q1[0], q2[0], p1[0], p2[0]]
    host = 1.7e9
    for k in range(frames):
        for row in range(3):
            if row == 0:
                state[0], state[2] = q1[k], p1[k]
            elif row == 1:
                state[1], state[3] = q2[k] * (-1 if k % 2 else 1), p2[k]
            host += 1e-5 if row else 8.3e-3
            lines.append(",".join(repr(float(v)) for v in [host, *np.concatenate(state)]))
    path.write_text("\n".join(lines) + "\n")
    return path, np.stack([q1, q2], axis=1)


def test_liberty_frames_units_and_dropouts(tmp_path):
    path, q = _liberty(tmp_path / "p.csv", 200, dropout=slice(50, 53))
    assert sniff(path) == "polhemus-liberty"
    step, report = read_recording(path)
    assert step.n_frames == 200 and step.sensor_ids == ["1", "2"]
    assert np.allclose(rotations.angle_between(step.quaternion, q), 0.0, atol=1e-7)
    assert np.allclose(step.position[0, 0], np.array([20.0, 5.0, 3.0]) * 0.0254)
    assert np.flatnonzero(~step.valid_mask[:, 1]).tolist() == [50, 51, 52] and step.valid_mask[:, 0].all()
    text = report.text()
    assert "dropped 201 rows" in text and "3 samples in 1 runs near (0, 0, 0)" in text
    assert "positions read as in" in text
    assert step.sample_rate_hz == pytest.approx(1 / (8.3e-3 + 2e-5), rel=1e-3)
    mm, _ = read_recording(path, unit="mm")
    assert np.allclose(mm.position[0, 0], np.array([20.0, 5.0, 3.0]) * 1e-3)


def test_liberty_bad_unit_refused(tmp_path):
    path, _ = _liberty(tmp_path / "p.csv", 10)
    with pytest.raises(CsvError, match="position unit 'ft'"):
        read_recording(path, unit="ft")


@pytest.mark.skipif(not HEAD.exists(), reason="shared/data is not beside the repository")
def test_real_head_trace():
    step, report = read_recording(HEAD)
    assert step.n_frames > 15_000 and 55 < step.sample_rate_hz < 62
    assert "sign continuous" in report.text()
    assert np.all(np.diff(step.time) > 0)


@pytest.mark.skipif(not LIBERTY.exists(), reason="shared/data is not beside the repository")
def test_real_liberty_dropouts_flagged():
    step, report = read_recording(LIBERTY / "Polhemus_90degX(clean)_data.csv")
    assert 119 < step.sample_rate_hz < 122
    bad = np.flatnonzero(~step.valid_mask[:, 1])
    assert len(bad) == 6 and step.valid_mask[:, 0].all()  # the six dropouts of sensor 2, nothing else
    assert np.all(np.linalg.norm(step.position[step.valid_mask], axis=-1) > 0.4)  # no (0, 0, 0) kept valid
    assert "flagged invalid" in report.text()


def test_liberty_positions_read_in_the_wrong_unit_are_refused_with_the_likely_one(tmp_path):
    path, _ = _liberty(tmp_path / "p.csv", 20)  # positions in inches, 20-30 in from the source
    with pytest.raises(CsvError, match=r"read as m, the sensors are .* m from the source.*likely in"):
        read_recording(path, unit="m")


def test_a_liberty_file_of_one_repeated_frame_is_refused_plainly(tmp_path):
    path, _ = _liberty(tmp_path / "p.csv", 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no NumPy warning on the way to the refusal
        with pytest.raises(CsvError, match="holds one tracker frame"):
            read_recording(path)
