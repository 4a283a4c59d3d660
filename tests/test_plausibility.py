"""Absurd values are refused with the likely cause, not carried through: units typed wrong, attributes outside
the documented set, incomplete files."""

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from ivc import lut
from ivc.errors import LutError, SessionError
from ivc.session.model import validate_step
from tests.helpers import make_step, survey_attrs

TABLE = Path(__file__).resolve().parents[1] / "sample_data" / "recordings" / "default_room_lut.h5"


def test_a_declared_position_typed_in_millimetres_is_refused_with_the_metres(rng):
    survey = make_step(rng)
    survey.attrs = survey_attrs() | {"declared_position": np.array([500.0, 0.0, 0.0])}
    with pytest.raises(SessionError, match=r"500 m from the source.*use 0\.5, 0, 0"):
        validate_step("cube_survey", survey)
    survey.attrs["declared_position"] = np.array([0.5, 0.0, 0.0])
    validate_step("cube_survey", survey)  # the same in metres is fine


@pytest.mark.parametrize(("attribute", "value", "message"), [
    ("hemisphere", "up", "hemisphere = 'up': must be one of"),
    ("length_unit", "mm", "length_unit = 'mm': ivc tables are in metres"),
])
def test_a_table_with_an_undocumented_attribute_is_refused(tmp_path, attribute, value, message):
    table = tmp_path / "table.h5"
    shutil.copyfile(TABLE, table)
    with h5py.File(table, "r+") as h5:
        h5.attrs[attribute] = value
    with pytest.raises(LutError, match=message):
        lut.read(table)


def test_a_table_without_its_fit_group_says_it_is_incomplete(tmp_path):
    table = tmp_path / "table.h5"
    shutil.copyfile(TABLE, table)
    with h5py.File(table, "r+") as h5:
        del h5["fit"]
    with pytest.raises(LutError, match=r"no /fit in the file: an incomplete look-up table") as error:
        lut.read(table)
    assert "Unable to" not in str(error.value) and "object" not in str(error.value)  # none of h5py's own text
    assert lut.read(TABLE).hemisphere == "+x"  # the intact table still reads


def test_a_scalar_signal_dataset_is_named_not_valid(rng):
    step = make_step(rng, with_pose=False)
    step.signal = np.float64(1.0)
    with pytest.raises(SessionError, match=r"/signal: shape \(\), expected \(frames, sensors, 3, 3\)"):
        validate_step("check", step)


def test_positions_in_another_unit_are_refused_by_frame_and_sensor(rng):
    step = make_step(rng, with_signal=False)
    step.valid[:] = True
    step.position[3, 2] *= 1000  # millimetres in a file of metres
    with pytest.raises(SessionError, match=r"frame 3, sensor 2 is .* m from the source"):
        validate_step("check", step)
