"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step, rate_warning
from ivc.collect.guide import StepReport, StepStatus, collect_protocol, collect_step
from ivc.collect.head_trace import read_head_trace
from ivc.collect.ilemt import IlemtRecording, read_ilemt
from ivc.collect.imports import ImportReport, read_import, read_recording, replay, sniff
from ivc.collect.plus import PlusError, PlusSequence, is_plus_sequence, read_plus, write_plus
from ivc.collect.polhemus import read_liberty_csv
from ivc.collect.replay import CsvColumns, CsvError, read_csv, read_csv_columns, write_csv
from ivc.collect.rig_csv import read_rig_csv, write_rig_csv
from ivc.collect.tracker_units import apply_tracker, apply_tracker_to_session

__all__ = ["CsvColumns", "CsvError", "IlemtRecording", "ImportReport", "PlusError", "PlusSequence", "StepReport",
           "StepStatus", "apply_tracker", "apply_tracker_to_session", "check_step", "collect_protocol", "collect_step",
           "is_plus_sequence", "rate_warning", "read_csv", "read_csv_columns", "read_head_trace", "read_ilemt",
           "read_import", "read_liberty_csv", "read_plus", "read_recording", "read_rig_csv", "replay", "sniff",
           "write_csv", "write_plus", "write_rig_csv"]
