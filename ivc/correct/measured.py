"""The corrector of a table for each kind of measurement (:mod:`ivc.fixtures.measurement`): the correct stage's
part of the one measurement model, kept here so that the model's module imports nothing above the fixtures."""

from __future__ import annotations

from ivc.correct.reported import PoseCorrector
from ivc.correct.solver import Corrector
from ivc.fixtures.measurement import Measurement, PoseInput, SignalInput
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

__all__ = ["CORRECTORS", "corrector_for"]

#: the corrector class of each kind of measurement, called as ``(table, hemisphere, interpolation, **options)``;
#: a new kind of input registers its corrector here
CORRECTORS: dict[type, type] = {SignalInput: Corrector, PoseInput: PoseCorrector}


def corrector_for(measurement: Measurement, table: LookupTable | GridField, hemisphere: str | None = None,
                  interpolation: str = "cubic", **options) -> Corrector | PoseCorrector:
    """The corrector that applies ``table`` to data of ``measurement``'s kind: a :class:`Corrector` for signals,
    a :class:`PoseCorrector` for reported poses. ``options``: that class's keyword arguments (``max_residual``;
    ``precision`` for signals, ``solver`` for reported poses, default the table's)."""
    return CORRECTORS[type(measurement)](table, hemisphere, interpolation, **options)
