"""The look-up table itself: the room's secondary field on a regular grid, its interpolation and its file.

Below the stages that use a table (:mod:`ivc.correct`, which solves poses in it) and the one that makes it
(:mod:`ivc.lut`, whose joint map and refinement solve poses in the table they are fitting); docs/architecture.md.
"""

from ivc.table.fit_report import FitReport
from ivc.table.grid import DEFAULT_SPACING, Grid, GridField
from ivc.table.lookup import LookupTable, LutError, read, write

__all__ = ["DEFAULT_SPACING", "FitReport", "Grid", "GridField", "LookupTable", "LutError", "read", "write"]
