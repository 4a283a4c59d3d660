import hashlib

import h5py
import numpy as np
import pytest

from ivc import dipole, session
from ivc.session import Session, SessionError
from tests.helpers import full_session, make_step, survey_attrs


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_write_read_is_bit_exact(tmp_path, rng):
    original = full_session(rng)
    path = tmp_path / "s.h5"
    session.write(original, path)
    back = session.read(path)
    assert back.hemisphere == "+x"
    assert list(back.steps) == list(original.steps)
    for name, step in original.steps.items():
        got = back.steps[name]
        for dataset in ("time", "signal", "position", "quaternion", "valid"):
            a, b = getattr(step, dataset), getattr(got, dataset)
            assert (a is None) == (b is None)
            if a is not None:
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        assert got.sensor_ids == step.sensor_ids
        assert got.sample_rate_hz == step.sample_rate_hz
        assert got.description == step.description
    np.testing.assert_array_equal(
        back.steps["cube_survey"].attrs["declared_position"], survey_attrs()["declared_position"]
    )
    assert back.truth["check"].position.tobytes() == original.truth["check"].position.tobytes()
    # rewriting what was read gives the same content again
    session.write(back, tmp_path / "again.h5")
    again = session.read(tmp_path / "again.h5")
    assert again.steps["wand_sweep"].signal.tobytes() == original.steps["wand_sweep"].signal.tobytes()


def test_file_layout_matches_the_format(tmp_path, rng):
    path = tmp_path / "s.h5"
    session.write(full_session(rng), path)
    with h5py.File(path) as h5:
        assert h5.attrs["ivc_format"] == "session"
        assert h5.attrs["ivc_format_version"] == 1
        assert h5.attrs["length_unit"] == "m"
        assert h5["steps/wand_sweep/signal"].shape == (50, 5, 3, 3)
        assert h5["steps/check/quaternion"].shape == (7, 3, 4)
        assert h5["steps/cube_calibration/valid"].dtype == bool
        assert h5["truth/check/position"].dtype == np.float64
        assert list(h5["steps/cube_calibration"].attrs["sensor_ids"]) == [f"s{i}" for i in range(8)]


def test_pose_only_step_rebuilds_signal(rng):
    step = make_step(rng, with_signal=False)
    S = step.signal_matrices()
    np.testing.assert_allclose(S, dipole.signal_from_pose(step.position, step.quaternion))


def test_add_step_never_overwrites_without_force(tmp_path, rng):
    path = tmp_path / "s.h5"
    first = make_step(rng)
    session.add_step(path, "cube_calibration", first)
    before = digest(path)
    with pytest.raises(FileExistsError, match="cube_calibration.*force=True"):
        session.add_step(path, "cube_calibration", make_step(rng))
    assert digest(path) == before
    session.add_step(path, "wand_calibration", make_step(rng, sensors=4))
    assert session.read(path).steps["cube_calibration"].signal.tobytes() == first.signal.tobytes()
    replacement = make_step(rng)
    session.add_step(path, "cube_calibration", replacement, force=True)
    assert session.read(path).steps["cube_calibration"].signal.tobytes() == replacement.signal.tobytes()
    with pytest.raises(FileExistsError):
        session.write(Session(), path)


def test_interrupted_write_leaves_previous_file(tmp_path, rng, monkeypatch):
    path = tmp_path / "s.h5"
    session.add_step(path, "cube_calibration", make_step(rng))
    before = digest(path)
    from ivc.session import io

    original = io._write_step

    def crash_midway(h5, name, step):
        h5.require_group("steps").create_group(name).create_dataset("time", data=step.time)
        raise KeyboardInterrupt("power cut")

    monkeypatch.setattr(io, "_write_step", crash_midway)
    with pytest.raises(KeyboardInterrupt):
        session.add_step(path, "wand_calibration", make_step(rng, sensors=4))
    monkeypatch.setattr(io, "_write_step", original)
    assert digest(path) == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.h5"]
    assert list(session.read(path).steps) == ["cube_calibration"]


def write_then_corrupt(tmp_path, rng, edit):
    path = tmp_path / "bad.h5"
    session.write(full_session(rng), path)
    with h5py.File(path, "r+") as h5:
        edit(h5)
    return path


def _replace(h5, name, data):
    del h5[name]
    h5[name] = data


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda h5: h5.attrs.__setitem__("ivc_format", "lut"), "ivc_format"),
        (lambda h5: h5.attrs.__setitem__("ivc_format_version", 2), "ivc_format_version = 2.*upgrade"),
        (lambda h5: h5.attrs.__setitem__("length_unit", "mm"), "length_unit"),
        (lambda h5: h5.attrs.__setitem__("hemisphere", "up"), "hemisphere"),
        (lambda h5: h5["steps/cube_calibration"].__delitem__("time"), "/steps/cube_calibration/time: missing"),
        (lambda h5: _replace(h5, "steps/wand_sweep/signal", np.zeros((50, 5, 3))), "/steps/wand_sweep/signal: shape"),
        (
            lambda h5: _replace(h5, "steps/wand_sweep/time", np.arange(49.0)),
            "/steps/wand_sweep/(signal|valid): 50 frames but time has 49",
        ),
        (
            lambda h5: _replace(h5, "steps/check/quaternion", np.ones((7, 3, 4))),
            "/steps/check/quaternion: .*not unit norm",
        ),
        (lambda h5: _replace(h5, "steps/check/valid", np.ones((7, 3), dtype=np.int8)), "/steps/check/valid: dtype"),
        (lambda h5: _replace(h5, "steps/check/time", -np.arange(7.0)), "/steps/check/time: goes backwards"),
        (lambda h5: h5["steps/cube_survey"].attrs.__delitem__("declared_position"), "declared_position: missing"),
        (lambda h5: _replace(h5, "truth/check/position", np.zeros((6, 3, 3))), "/truth/check/position: shape"),
        (lambda h5: h5["steps/wand_sweep"].attrs.__setitem__("sample_rate_hz", -1.0), "sample_rate_hz"),
        (lambda h5: h5["steps"].move("check", "cheque"), "/steps/cheque: unknown step"),
    ],
)
def test_malformed_files_name_the_dataset(tmp_path, rng, edit, message):
    path = write_then_corrupt(tmp_path, rng, edit)
    with pytest.raises(SessionError, match=message):
        session.read(path)


def test_nan_only_allowed_in_invalid_samples(tmp_path, rng):
    step = make_step(rng)
    step.valid[:] = True
    step.valid[3, 2] = False
    step.signal[3, 2] = np.nan
    step.position[3, 2] = np.inf
    session.add_step(tmp_path / "ok.h5", "cube_calibration", step)  # a dropout is fine
    step.signal[4, 1, 0, 0] = np.nan
    with pytest.raises(
        SessionError, match=r"/steps/cube_calibration/signal: 1 valid samples hold NaN.*frame 4, sensor 1"
    ):
        session.add_step(tmp_path / "bad.h5", "cube_calibration", step)
    assert not (tmp_path / "bad.h5").exists()


def test_in_memory_validation_errors(rng):
    step = make_step(rng, sensors=5)
    with pytest.raises(SessionError, match="the interpolation cube has 8"):
        session.model.validate_step("cube_calibration", step)
    no_pose = make_step(rng, with_signal=False)
    no_pose.quaternion = None
    with pytest.raises(SessionError, match="quaternion: missing"):
        session.model.validate_step("check", no_pose)
    survey = make_step(rng)
    survey.attrs = survey_attrs()
    steps = {"wand_calibration": make_step(rng, sensors=4), "wand_sweep": make_step(rng, sensors=5)}
    with pytest.raises(SessionError, match="same wand"):
        Session(steps=steps).validate()


def test_not_hdf5_and_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        session.read(tmp_path / "nope.h5")
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    with pytest.raises(SessionError, match="not an HDF5 file"):
        session.read(junk)


def test_missing_for_fit(rng):
    s = full_session(rng)
    assert s.missing_for_fit() == []
    del s.steps["wand_sweep"]
    assert any("ivc collect wand_sweep" in m for m in s.missing_for_fit())
    del s.steps["cube_survey"].attrs["declared_quaternion"]
    lacks = s.lacks_for_fit()
    assert [lack.step for lack in lacks] == ["wand_sweep", "cube_survey"]
    assert lacks[0].short == "no wand_sweep step"
    assert "--declared-quaternion" in lacks[1].advice
    assert s.missing_for_fit() == [lack.advice for lack in lacks]
