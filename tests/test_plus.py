"""PLUS sequence files: the two real recordings import with every frame, status and timestamp; ivc's own
files are read back by ivc and by ITK (SimpleITK); malformed files are refused with the field named."""

import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from ivc import rotations
from ivc import session as session_io
from ivc.cli import cli
from ivc.collect import PlusError, read_csv, read_plus, replay, write_plus
from ivc.correct import PoseCorrector
from ivc.lut import write as write_lut

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "plus"
FILES = ["Prostate10_tracker.igs.mha", "WaterTankBottomTranslationTrackerBuffer-trimmed.igs.mha"]


def real(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} is not here (shared data beside the repository)")
    return path


def independent_parse(path: Path) -> dict:
    """Every Seq_Frame field of the file, by a regular expression over its text: {(frame, field): value}."""
    text = path.read_bytes().decode("latin-1")
    return {(int(m[1]), m[2]): m[3].strip() for m in re.finditer(r"^Seq_Frame(\d+)_(\S+) = (.*)$", text, re.M)}


@pytest.mark.parametrize("name", FILES)
def test_the_real_plus_files_import_with_every_frame_status_and_timestamp(name):
    path = real(name)
    fields = independent_parse(path)
    sequence = read_plus(path)
    step = sequence.step
    frames = 1 + max(k for k, _ in fields)
    declared = int(re.search(r"^DimSize = .* (\d+)\s*$", path.read_text("latin-1"), re.M)[1])
    assert step.n_frames == frames == declared
    transforms = sorted({f[:-len("Transform")] for _, f in fields if f.endswith("Transform")})
    assert step.sensor_ids == [t for t in sequence.sensor_names] and sorted(step.sensor_ids) == transforms
    for k in range(frames):
        assert step.time[k] == float(fields[k, "Timestamp"])
        assert sequence.unfiltered_time[k] == float(fields[k, "UnfilteredTimestamp"])
        assert sequence.frame_numbers[k] == int(fields[k, "FrameNumber"])
        for n, sensor in enumerate(step.sensor_ids):
            m = np.array(fields[k, sensor + "Transform"].split(), float).reshape(4, 4)
            assert step.valid[k, n] == (fields[k, sensor + "TransformStatus"] == "OK")
            np.testing.assert_allclose(step.position[k, n], m[:3, 3] / 1000.0, rtol=0, atol=1e-15)
            R = rotations.to_matrix(step.quaternion[k, n])
            # the nearest rotation to the printed matrix (orthonormal to 1e-4 in one file), by scipy's own method
            np.testing.assert_allclose(R, Rotation.from_matrix(m[:3, :3]).as_matrix(), atol=1e-7)
    assert step.sample_rate_hz > 0 and np.all(np.diff(step.time) > 0)


def test_collect_replays_a_plus_file_into_a_session(tmp_path):
    path = real(FILES[1])
    result = CliRunner().invoke(cli, ["collect", "check", "--source", f"replay:{path}", "-o", str(tmp_path / "s.h5")])
    assert result.exit_code == 0, result.output
    step = session_io.read(tmp_path / "s.h5").steps["check"]
    expected, _ = replay(path, "check")
    np.testing.assert_array_equal(step.position, expected.position)
    assert step.sensor_ids == ["ProbeToTracker", "ReferenceToTracker", "StylusToTracker"]


@pytest.mark.slow  # `ivc correct` of a PLUS sequence file, end to end
def test_correct_writes_the_sequence_back_with_ivc_transforms_added(exact_table, tmp_path):  # noqa: F811
    path = real(FILES[0])
    lut_file = tmp_path / "lut.h5"
    write_lut(exact_table, lut_file)
    out = tmp_path / "corrected.igs.mha"
    result = CliRunner().invoke(cli, ["correct", str(lut_file), str(path), "-o", str(out)])
    assert result.exit_code == 0, result.output
    before, after = independent_parse(path), independent_parse(out)
    assert {k: v for k, v in after.items() if "Ivc" not in k[1]} == before  # nothing of the original changed
    original = read_plus(path)
    # reported poses only: corrected through the pose path, not from signals rebuilt from them
    expected = PoseCorrector(exact_table).batch(original.step.position, original.step.quaternion,
                                                original.step.valid_mask)
    again = read_plus(out)
    assert again.step.sensor_ids == original.step.sensor_ids  # the new transforms are to another frame
    assert again.other_transforms == ["ToolToTrackerIvcTransform"]
    assert again.data == original.data
    for k in range(original.step.n_frames):
        flags = int(after[k, "ToolToTrackerIvcFlags"])
        assert flags == expected.flags[k, 0]
        assert after[k, "ToolToTrackerIvcTransformStatus"] == ("OK" if flags == 0 else "INVALID")
        m = np.array(after[k, "ToolToTrackerIvcTransform"].split(), float).reshape(4, 4)
        if flags == 0:
            np.testing.assert_allclose(m[:3, 3] / 1000, expected.position[k, 0], atol=1e-9)
    header = out.read_text("latin-1").splitlines()
    assert header[-1].startswith("0000000000") and header[-2] == "ElementDataFile = LOCAL"
    custom = next(line for line in header if line.startswith("CustomFrameFieldNames"))
    assert "ToolToTrackerIvcTransform" in custom and "ToolToTrackerIvcTransformStatus" in custom


def test_itk_reads_what_ivc_writes(tmp_path):
    sitk = pytest.importorskip("SimpleITK")
    path = real(FILES[0])
    sequence = read_plus(path)
    out = tmp_path / "copy.igs.mha"
    write_plus(sequence, out, {"{tool}To{tracker}Ivc": (sequence.step.position, sequence.step.quaternion, None)})
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(out))
    reader.ReadImageInformation()
    assert reader.GetSize() == (1, 1, 10)
    m = np.array(reader.GetMetaData("Seq_Frame0003_ToolToTrackerIvcTransform").split(), float).reshape(4, 4)
    np.testing.assert_allclose(m[:3, 3] / 1000, sequence.step.position[3, 0], atol=1e-9)
    pixels = sitk.GetArrayFromImage(sitk.ReadImage(str(out)))
    original = sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
    np.testing.assert_array_equal(pixels, original)


def test_predict_reads_a_plus_file(tmp_path):
    path = real(FILES[1])
    result = CliRunner().invoke(cli, ["predict", str(path), "-o", str(tmp_path / "p.csv"), "--horizon", "50ms"])
    assert result.exit_code == 0, result.output
    step = read_csv(tmp_path / "p.csv")
    assert step.n_frames == 801 and step.n_sensors == 3
    np.testing.assert_allclose(step.position, read_plus(path).step.position, atol=1e-12)


SMALL = """ObjectType = Image
NDims = 3
DimSize = 0 0 {frames}
ElementType = MET_UCHAR
{body}ElementDataFile = LOCAL
"""


def _frame(k, t, status="OK", matrix="1 0 0 100 0 1 0 0 0 0 1 0 0 0 0 1"):
    return (f"Seq_Frame{k:04d}_ToolToTrackerTransform = {matrix}\n"
            f"Seq_Frame{k:04d}_ToolToTrackerTransformStatus = {status}\n"
            f"Seq_Frame{k:04d}_Timestamp = {t}\n")


@pytest.mark.parametrize("body, frames, words", [
    (_frame(0, 1.0) + _frame(2, 2.0), 2, "frame 0001 is missing"),
    (_frame(0, 1.0) + _frame(1, 2.0), 3, "declares 3 frames"),
    (_frame(0, 2.0) + _frame(1, 1.0), 2, "time order"),
    (_frame(0, 1.0) + _frame(1, 1.0), 2, "time order"),
    (_frame(0, 1.0, matrix="2 0 0 100 0 1 0 0 0 0 1 0 0 0 0 1"), 1, "not a rigid transform"),
    (_frame(0, 1.0, matrix="1 0 0"), 1, "expected 16 numbers"),
    ("Seq_Frame0000_Timestamp = 1\n", 1, "no <Tool>To<Tracker>Transform"),
    ("", 0, "no Seq_FrameNNNN_ fields"),
])
def test_malformed_sequences_are_refused_with_the_field_named(tmp_path, body, frames, words):
    path = tmp_path / "bad.igs.mha"
    path.write_text(SMALL.format(frames=frames, body=body))
    with pytest.raises(PlusError, match=words):
        read_plus(path)


def test_a_status_other_than_ok_is_invalid_whatever_the_matrix(tmp_path):
    path = tmp_path / "missing.igs.mha"
    path.write_text(SMALL.format(frames=3, body=_frame(0, 1.0) + _frame(1, 1.5, "MISSING", "0 " * 16)
                                 + _frame(2, 2.0, "OUT_OF_VIEW")))
    step = read_plus(path).step
    assert step.valid[:, 0].tolist() == [True, False, False]
    assert step.position[0, 0].tolist() == [0.1, 0.0, 0.0]


def test_info_summarises_a_plus_file():
    path = real(FILES[1])
    result = CliRunner().invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, result.output
    assert "PLUS sequence, 801 frames x 3 sensors" in result.output


NRRD = b"""NRRD0004
# Complete NRRD file format specification at:
type: uint8
dimension: 3
sizes: 1 1 2
kinds: domain domain list
encoding: raw
Seq_Frame0000_ToolToTrackerTransform:=1 0 0 100 0 1 0 0 0 0 1 0 0 0 0 1
Seq_Frame0000_ToolToTrackerTransformStatus:=OK
Seq_Frame0000_Timestamp:=1.0
Seq_Frame0001_ToolToTrackerTransform:=0 -1 0 120 1 0 0 5 0 0 1 0 0 0 0 1
Seq_Frame0001_ToolToTrackerTransformStatus:=OK
Seq_Frame0001_Timestamp:=1.5

\x07\x09"""


def test_an_nrrd_sequence_reads_and_writes_back_for_pynrrd(tmp_path):
    nrrd = pytest.importorskip("nrrd")
    path = tmp_path / "in.seq.nrrd"
    path.write_bytes(NRRD)
    sequence = read_plus(path)
    assert sequence.nrrd and sequence.data == b"\x07\x09"
    np.testing.assert_allclose(sequence.step.position[:, 0], [[0.1, 0, 0], [0.12, 0.005, 0]])
    out = tmp_path / "out.seq.nrrd"
    write_plus(sequence, out, {"{tool}To{tracker}Ivc": (sequence.step.position, sequence.step.quaternion, None)})
    data, header = nrrd.read(str(out))
    assert data.shape == (1, 1, 2) and data.ravel().tolist() == [7, 9]
    m = np.array(header["Seq_Frame0001_ToolToTrackerIvcTransform"].split(), float).reshape(4, 4)
    np.testing.assert_allclose(m[:3, 3], [120, 5, 0], atol=1e-6)
    again = read_plus(out)
    np.testing.assert_array_equal(again.step.position, sequence.step.position)
