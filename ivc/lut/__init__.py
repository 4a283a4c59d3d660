"""Stage 4: the look-up table of the room's secondary field, fitted from the wand's samples."""

from ivc.lut.build import METHODS, FitOptions, fit_lut
from ivc.lut.grid import DEFAULT_SPACING, Grid, GridField
from ivc.lut.table import LookupTable, LutError, read, write

__all__ = ["DEFAULT_SPACING", "METHODS", "FitOptions", "Grid", "GridField", "LookupTable", "LutError", "fit_lut",
           "read", "write"]
