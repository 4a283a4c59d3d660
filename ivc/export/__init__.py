"""Stage 6b: the look-up table in the formats trackers, 3D Slicer, ParaView and Vrui read (docs/export.md).

``export(table, fmt, path)`` writes one format atomically; :data:`FORMATS` names them all.
"""

from ivc.export.formats import (
    FORMATS,
    REPORTED_GRID_FORMATS,
    SLICER_TO_PARENT_CLASS,
    UNITS,
    VRUI_MARGIN,
    ExportError,
    csv_sidecar,
    export,
    resolve_unit,
)

__all__ = ["FORMATS", "REPORTED_GRID_FORMATS", "SLICER_TO_PARENT_CLASS", "UNITS", "VRUI_MARGIN", "ExportError",
           "csv_sidecar", "export", "resolve_unit"]
