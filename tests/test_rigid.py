"""Sensors of one rigid body decide each other's branch (ivc.correct.rigid, docs/trust.md): the body's consensus,
the flags it adds, a body's geometry from poses or a JSON file, and `correct_file(..., rigid_body=...)`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ivc import rotations
from ivc.app.correct import CorrectOptions, correct_file, load_rigid_body
from ivc.collect.replay import write_csv
from ivc.correct import HIGH_RESIDUAL, LOW_PRECISION, PoseCorrector
from ivc.correct.rigid import agree_with_body
from ivc.correct.solver import Correction
from ivc.errors import InputError, OptionsError
from ivc.fixtures.wand import WandCalibration
from ivc.lut import write as write_lut
from ivc.pose.tracker_solver import distortion
from ivc.session import Step
from tests.helpers import CENTRE

#: a four-sensor tool in its own frame (m)
LAYOUT = np.array([[0.0, 0.0, 0.0], [0.06, 0.0, 0.0], [0.0, 0.05, 0.01], [0.03, 0.02, 0.07]])


def body(rng) -> tuple[WandCalibration, np.ndarray]:
    q = rotations.random(len(LAYOUT), rng)
    return WandCalibration.from_poses(LAYOUT, q), q


def moving(calibration: WandCalibration, rng, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The body's sensors' poses (F, W, 3), (F, W, 4) along random body poses near CENTRE."""
    r0 = CENTRE + rng.uniform(-0.05, 0.05, (frames, 3))
    T0 = rotations.to_matrix(rotations.random(frames, rng))
    position, rotation = calibration.propagate(r0, T0)
    return position, rotations.from_matrix(rotation)


def correction(position, quaternion, flags=None) -> Correction:
    F, W = position.shape[:2]
    return Correction(position.copy(), quaternion.copy(), np.zeros((F, W), np.uint8) if flags is None else flags,
                      np.zeros((F, W)), np.zeros((F, W), np.int64))


def test_a_body_from_its_sensors_poses_is_their_poses_in_sensor_0s_frame(rng):
    calibration, q = body(rng)
    T = rotations.to_matrix(q)
    np.testing.assert_allclose(calibration.positions, (LAYOUT - LAYOUT[0]) @ T[0], atol=1e-15)
    np.testing.assert_allclose(calibration.rotations, T[0].T @ T, atol=1e-15)
    r0, T0 = CENTRE[None], rotations.to_matrix(rotations.random(1, rng))
    position, rotation = calibration.propagate(r0, T0)  # the same body anywhere: sensor 0 carries the others
    apart = np.linalg.norm(position[0, :, None] - position[0, None], axis=-1)
    np.testing.assert_allclose(apart, np.linalg.norm(LAYOUT[:, None] - LAYOUT[None], axis=-1), atol=1e-15)
    with pytest.raises(InputError, match="at least two sensors"):
        WandCalibration.from_poses(LAYOUT[:1], q[:1])


def test_a_sensor_its_body_disagrees_with_is_flagged_and_nothing_else(rng):
    calibration, _ = body(rng)
    position, quaternion = moving(calibration, rng, 60)
    position += rng.normal(0, 1e-4, position.shape)  # corrected poses at the tracker's noise
    position[:10, 2] += [0.2, 0.0, 0.0]  # sensor 2 on the map's other branch
    quaternion[10:15, 3] = rotations.from_matrix(rotations.to_matrix(quaternion[10:15, 3])
                                                 @ rotations.to_matrix(np.array([[0.98, 0.2, 0.0, 0.0]])))
    flags = np.zeros((60, 4), np.uint8)
    flags[20:25, 1:] = LOW_PRECISION  # one trusted sensor left: nothing to decide with
    flags[25:30, 2:] = LOW_PRECISION  # two left that agree: kept
    out = correction(position, quaternion, flags)
    consensus = calibration.consensus(position, quaternion, flags == 0)
    flagged = agree_with_body(out, calibration)
    expected = np.zeros((60, 4), bool)
    expected[:10, 2] = True
    expected[10:15, 3] = True
    expected[20:25, 0] = True
    np.testing.assert_array_equal(flagged, expected)
    np.testing.assert_array_equal(out.flags[expected], HIGH_RESIDUAL)
    np.testing.assert_array_equal(out.flags[~expected], flags[~expected])  # the other flags untouched
    # the consensus is sensor 0's pose where a set agrees, to the noise
    kept = consensus.kept
    assert kept.sum() == 55 and not kept[20:25].any()
    assert np.max(np.linalg.norm(consensus.position[kept] - position[kept, 0], axis=1)) < 1e-3
    with pytest.raises(InputError, match="rigid body of 4 sensors"):
        agree_with_body(correction(position[:, :3], quaternion[:, :3]), calibration)


def test_correct_file_flags_a_sensor_its_rigid_body_disagrees_with(exact_table, rng, tmp_path):
    """A CSV of a four-sensor tool's reported poses, one sensor's shifted in 20 frames (still in the map, so the
    table trusts it): with the tool's geometry as JSON, those 20 are flagged and no other sample is."""
    calibration, q = body(rng)
    true_position, true_quaternion = moving(calibration, rng, 80)
    r = true_position.reshape(-1, 3)
    v, C = distortion(r, exact_table.field()(r))
    reported = rotations.from_matrix(C @ rotations.to_matrix(true_quaternion.reshape(-1, 4)))
    v, reported = v.reshape(80, 4, 3), reported.reshape(80, 4, 4)
    v[30:50, 1] += [0.0, 0.0, 0.03]
    step = Step(time=np.arange(80) / 240.0, position=v, quaternion=reported)
    write_csv(step, tmp_path / "tool.csv")
    write_lut(exact_table, tmp_path / "lut.h5")
    (tmp_path / "tool.json").write_text(json.dumps({"positions": LAYOUT.tolist(), "quaternions": q.tolist()}))
    plain = correct_file(tmp_path / "lut.h5", tmp_path / "tool.csv", tmp_path / "plain.csv")
    checked = correct_file(tmp_path / "lut.h5", tmp_path / "tool.csv", tmp_path / "checked.csv",
                           CorrectOptions(rigid_body=tmp_path / "tool.json"))
    before, after = plain.corrections["tool.csv"].flags, checked.corrections["tool.csv"].flags
    assert np.all(before == 0)  # the shifted sensor is trusted without its body
    expected = np.zeros((80, 4), bool)
    expected[30:50, 1] = True
    np.testing.assert_array_equal(after != 0, expected)
    np.testing.assert_array_equal(after[expected], HIGH_RESIDUAL)
    assert PoseCorrector(exact_table).batch(v[30:50, 1], reported[30:50, 1]).flags.max() == 0


def test_a_rigid_body_file_that_is_not_one_gets_a_clear_error(tmp_path):
    (tmp_path / "bad.json").write_text('{"positions": [[0, 0, 0]]}')
    with pytest.raises(OptionsError, match="not a rigid body"):
        load_rigid_body(tmp_path / "bad.json")
    (tmp_path / "one.json").write_text('{"positions": [[0, 0, 0]], "quaternions": [[1, 0, 0, 0]]}')
    with pytest.raises(InputError, match="at least two sensors"):
        load_rigid_body(tmp_path / "one.json")


def test_a_sessions_wand_calibration_is_a_rigid_body(small_session, tmp_path):
    from ivc.session import write as write_session

    _, session = small_session
    write_session(session, tmp_path / "s.h5")
    loaded = load_rigid_body(tmp_path / "s.h5")
    expected = WandCalibration.from_step(session.steps["wand_calibration"], session.hemisphere)
    np.testing.assert_allclose(loaded.positions, expected.positions)
    np.testing.assert_allclose(loaded.rotations, expected.rotations)
    write_session(type(session)(session.hemisphere, {"check": session.steps["check"]}, {}, {}), tmp_path / "c.h5")
    with pytest.raises(OptionsError, match="no wand_calibration step"):
        load_rigid_body(tmp_path / "c.h5")


def test_the_live_loop_flags_a_sensor_its_rigid_body_disagrees_with(exact_table, rng):
    """A round of the live loop (TRANSFORM poses of a four-sensor tool): all trusted as they are; one sensor
    shifted is flagged (4); with one sensor missing from the round the other three still decide."""
    import socket

    from ivc.correct import Corrector
    from ivc.live import LiveCorrector

    calibration, _ = body(rng)
    names = ["s0", "s1", "s2", "s3"]
    listener = socket.create_server(("127.0.0.1", 0))
    with pytest.raises(OptionsError, match="device names in its order"):
        LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0), rigid_body=calibration)
    live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0), sensors=names,
                         pose_corrector=PoseCorrector(exact_table), background_compile=False,
                         rigid_body=calibration)
    try:
        true_position, true_quaternion = moving(calibration, rng, 3)
        v, C = distortion(true_position.reshape(-1, 3), exact_table.field()(true_position.reshape(-1, 3)))
        Q = C @ rotations.to_matrix(true_quaternion.reshape(-1, 4))
        v, Q = v.reshape(3, 4, 3), Q.reshape(3, 4, 3, 3)

        def round_(frame, shifted=None, missing=None):
            before = live.stats.flagged
            position = v[frame].copy()
            if shifted is not None:
                position[shifted] += [0.0, 0.0, 0.03]
            samples = [(name, 1000.0 + frame, None, (position[n], Q[frame, n]))
                       for n, name in enumerate(names) if n != missing]
            live._correct_round(samples)
            return live.stats.flagged - before

        assert round_(0) == 0
        assert round_(1, shifted=1) == 1
        starts = live.pose_corrector.warm_starts(names)  # the flagged sensor's track does not continue
        assert np.isnan(starts[1]).all() and np.isfinite(starts[[0, 2, 3]]).all()
        assert round_(2, shifted=2, missing=3) == 1
    finally:
        live.close()
        listener.close()
