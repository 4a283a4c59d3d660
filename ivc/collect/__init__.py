"""Recording the protocol: from the simulator or a real tracker's recording, with checks."""

from ivc.collect.checks import check_step
from ivc.collect.replay import CsvError, read_csv, replay, write_csv

__all__ = ["CsvError", "check_step", "read_csv", "replay", "write_csv"]
