"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step
from ivc.collect.head_trace import read_head_trace
from ivc.collect.imports import ImportReport, read_import, read_recording, sniff
from ivc.collect.polhemus import read_liberty_csv
from ivc.collect.replay import CsvError, read_csv, replay, write_csv

__all__ = ["CsvError", "ImportReport", "check_step", "read_csv", "read_head_trace", "read_import",
           "read_liberty_csv", "read_recording", "replay", "sniff", "write_csv"]
