"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step, rate_warning
from ivc.collect.ilemt import IlemtRecording, read_ilemt
from ivc.collect.plus import PlusError, PlusSequence, is_plus_sequence, read_plus, write_plus
from ivc.collect.replay import CsvColumns, CsvError, read_csv, read_csv_columns, replay, write_csv
from ivc.collect.rig_csv import read_rig_csv, write_rig_csv
from ivc.collect.tracker_units import apply_tracker, apply_tracker_to_session

__all__ = ["CsvColumns", "CsvError", "IlemtRecording", "PlusError", "PlusSequence", "apply_tracker",
           "apply_tracker_to_session", "check_step", "is_plus_sequence", "rate_warning", "read_csv",
           "read_csv_columns", "read_ilemt", "read_plus", "read_rig_csv", "replay", "write_csv", "write_plus",
           "write_rig_csv"]
