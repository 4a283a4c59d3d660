"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step, rate_warning
from ivc.collect.replay import CsvColumns, CsvError, read_csv, read_csv_columns, replay, write_csv

__all__ = ["CsvColumns", "CsvError", "check_step", "rate_warning", "read_csv", "read_csv_columns", "replay",
           "write_csv"]
