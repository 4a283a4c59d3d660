"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step
from ivc.collect.ilemt import IlemtRecording, read_ilemt
from ivc.collect.replay import CsvError, read_csv, replay, write_csv
from ivc.collect.rig_csv import read_rig_csv, write_rig_csv
from ivc.collect.tracker_units import apply_tracker, apply_tracker_to_session

__all__ = ["CsvError", "IlemtRecording", "apply_tracker", "apply_tracker_to_session", "check_step", "read_csv",
           "read_ilemt", "read_rig_csv", "replay", "write_csv", "write_rig_csv"]
