"""Fitting the look-up table of the room's secondary field from the wand's samples (the table itself: :mod:`ivc.table`).

The fitters (:class:`HarmonicFit`, :class:`PolyFit`, :class:`SourcesFit`) share one interface (:class:`Fitter`) and one
blocked cross-validation (:class:`BlockedKFold`); docs/lut.md, "Adding a fitter", describes both.
A session with extension sweeps is mapped over its whole working volume by :func:`fit_joint`.
"""

from ivc.lut.build import METHODS, FitOptions, fit_lut
from ivc.lut.coverage import box_coverage
from ivc.lut.cross_validation import BlockedKFold, cross_validate, held_out_score
from ivc.lut.fit_harmonic import HarmonicFit, HarmonicModel
from ivc.lut.fit_poly import PolyFit
from ivc.lut.fit_sources import SourceModel, SourcesFit
from ivc.lut.fitter import FITTERS, Fitter, fit_table, make_fitter, register
from ivc.lut.joint import JointMap, JointOptions, fit_joint, solve_wand, solve_wand_table
from ivc.lut.refine import MapFit, fit_map, refine_map
from ivc.lut.samples import FieldSamples
from ivc.lut.signal_noise import SignalNoise, measure_signal_noise
from ivc.table.fit_report import FitReport
from ivc.table.grid import DEFAULT_SPACING, Grid, GridField
from ivc.table.lookup import LookupTable, LutError, read, write

__all__ = ["DEFAULT_SPACING", "FITTERS", "METHODS", "BlockedKFold", "FieldSamples", "FitOptions", "FitReport", "Fitter",
           "Grid", "GridField", "HarmonicFit", "HarmonicModel", "JointMap", "JointOptions", "LookupTable", "LutError",
           "MapFit", "PolyFit", "SignalNoise", "SourceModel", "SourcesFit", "box_coverage", "cross_validate",
           "fit_joint", "fit_lut", "fit_map", "fit_table", "held_out_score", "make_fitter", "measure_signal_noise",
           "read", "refine_map", "register", "solve_wand", "solve_wand_table", "write"]
