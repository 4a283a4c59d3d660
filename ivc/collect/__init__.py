"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step, rate_warning
from ivc.collect.plus import PlusError, PlusSequence, is_plus_sequence, read_plus, write_plus
from ivc.collect.replay import CsvColumns, CsvError, read_csv, read_csv_columns, replay, write_csv

__all__ = ["CsvColumns", "CsvError", "PlusError", "PlusSequence", "check_step", "is_plus_sequence", "rate_warning",
           "read_csv", "read_csv_columns", "read_plus", "replay", "write_csv", "write_plus"]
