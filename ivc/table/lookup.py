"""The look-up table of the room's secondary field, and its HDF5 file (docs/lut.md, "The table file").

A table holds, per node of a regular grid, the nine components of the source-frame
secondary field ``G`` (same normalised units as ``f_D``, docs/math.md §1), whether the node
is supported by data, and how many samples supported it; plus how it was fitted and
from what. Nothing in it is read from ``/truth``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ivc.dipole import HEMISPHERES
from ivc.errors import IvcError, LutError
from ivc.files import atomic_path
from ivc.session.io import open_ivc_file
from ivc.table.fit_report import FitReport
from ivc.table.grid import Grid, GridField

FORMAT_NAME = "lut"
FORMAT_VERSION = 1
COMPONENTS = ("Gxx", "Gxy", "Gxz", "Gyx", "Gyy", "Gyz", "Gzx", "Gzy", "Gzz")


#: what the values G are, in the words every file carries
FIELD_UNIT = ("normalised dipole units: those of the dipole model f_D(r) = (3 r r^T / |r|^2 - I) / |r|^3 with r in "
              "metres (column j: the field of source coil j; on a coil's axis at 1 m its component along the axis "
              "is 2); the secondary field G is in the same units")


@dataclass
class LookupTable:
    """``values`` (nx, ny, nz, 3, 3): ``G[i, j]`` = field component ``i`` of source coil ``j``;
    ``valid`` (nx, ny, nz) bool; ``support`` (nx, ny, nz) int: samples within one cell of the node.

    ``fit``: method, degree, cross-validation score, samples used and dropped, refinement
    history. ``provenance``: input file and its SHA-256, parameters, ivc version, time.
    ``hemisphere``: the session's declared hemisphere, used to seed corrections.
    """

    grid: Grid
    values: np.ndarray
    valid: np.ndarray
    support: np.ndarray
    hemisphere: str = "+x"
    fit: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        for name in ("values", "valid", "support"):
            kind = np.asarray(getattr(self, name)).dtype.kind
            if kind not in "biuf":
                raise LutError(f"table {name}: expected numbers, got dtype {np.asarray(getattr(self, name)).dtype}")
        self.values = np.asarray(self.values, float)
        self.valid = np.asarray(self.valid, bool)
        support = np.asarray(self.support)
        if support.dtype.kind == "f" and not np.all(np.isfinite(support) & (support == np.round(support))):
            raise LutError("table support: expected whole numbers of samples, got NaN, inf or fractions")
        self.support = support.astype(np.int64)
        shape = self.grid.shape
        if self.values.shape != (*shape, 3, 3) or self.valid.shape != shape or self.support.shape != shape:
            raise LutError(f"table arrays {self.values.shape}, {self.valid.shape}, {self.support.shape} do not "
                           f"match the grid {shape}")
        if not self.valid.any():
            raise LutError("the table has no valid node: no data supports any part of the grid")
        if not np.all(np.isfinite(self.values[self.valid])):
            raise LutError("the table has non-finite values at valid nodes")

    @property
    def report(self) -> FitReport:
        """The fit record (``fit``) typed, the same fields for every fit path
        (:class:`~ivc.table.fit_report.FitReport`)."""
        try:
            return FitReport.from_dict(self.fit)
        except (KeyError, TypeError) as error:
            raise LutError(f"the table's fit record is incomplete ({error}): it was not made by a fit path of "
                           "ivc.lut.fit_lut; fit it again with `ivc fit`") from None

    @property
    def signal_noise(self) -> float | None:
        """The tracker's white noise per signal entry that the fit measured on the session's static steps
        (``fit["signal_noise"]``, ``ivc.lut.signal_noise``), or None when the table records none."""
        noise = self.fit.get("signal_noise")
        return float(noise["sigma"]) if noise else None

    @property
    def map_error(self) -> tuple[float, float] | None:
        """The map's own RMS error that its fit measured, in the reported pose (position m, orientation rad;
        ``fit["map_error"]``, :mod:`ivc.lut.map_error`), or None when the table records none (fits from
        signals, older tables)."""
        error = self.fit.get("map_error")
        if not error:
            return None
        return 1e-3 * float(error["position_mm"]), 1e-3 * float(error["orientation_mrad"])

    def field(self, interpolation: str = "cubic") -> GridField:
        """The interpolated field ``g(r)`` with its Jacobian and the mapped-volume test."""
        return GridField(self.grid, self.values, self.valid, interpolation)

    @property
    def mapped_fraction(self) -> float:
        return float(self.valid.mean())


def write(table: LookupTable, path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Write ``table`` atomically; refuse to replace an existing file unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs.update(ivc_format=FORMAT_NAME, ivc_format_version=FORMAT_VERSION, length_unit="m",
                        hemisphere=table.hemisphere, field_unit=FIELD_UNIT)
        grid = h5.create_group("grid")
        grid.attrs.update(origin=table.grid.origin, spacing=table.grid.spacing, shape=np.array(table.grid.shape),
                          index_order="x slowest, z fastest (Himberg 2010, eq. 105)")
        h5.create_dataset("values", data=table.values, compression="gzip", shuffle=True)
        h5["values"].attrs["components"] = np.array(COMPONENTS, dtype=h5py.string_dtype())
        h5.create_dataset("valid", data=table.valid, compression="gzip")
        h5.create_dataset("support", data=table.support.astype(np.int32), compression="gzip")
        h5.create_group("fit").attrs["json"] = json.dumps(table.fit)
        h5.create_group("provenance").attrs["json"] = json.dumps(table.provenance)


def read(path: str | os.PathLike) -> LookupTable:
    """Read a table written by :func:`write`; errors name the file and what is wrong."""
    path = Path(path)
    with open_ivc_file(path, FORMAT_NAME, FORMAT_VERSION, "look-up table", LutError,
                       "; make one with `ivc fit`") as (h5, attrs):
        lacking = [name for name in ("grid", "values", "valid", "support", "fit", "provenance") if name not in h5]
        if lacking:
            raise LutError(f"{path}: no /{lacking[0]} in the file: an incomplete look-up table (interrupted or "
                           "written by something else); make a new one with `ivc fit`")
        hemisphere = str(attrs.get("hemisphere", "+x"))
        if hemisphere not in HEMISPHERES:
            raise LutError(f"{path}: / attribute hemisphere = {hemisphere!r}: must be one of {', '.join(HEMISPHERES)} "
                           "(docs/conventions.md); make a new table with `ivc fit`")
        unit = str(attrs.get("length_unit", "m"))
        if unit != "m":
            raise LutError(f"{path}: / attribute length_unit = {unit!r}: ivc tables are in metres; a table in other "
                           "units is not ivc's (convert it, or make a new one with `ivc fit`)")
        try:
            g = h5["grid"].attrs
            grid = Grid(np.asarray(g["origin"]), float(g["spacing"]), tuple(np.asarray(g["shape"])))
            return LookupTable(grid, h5["values"][()], h5["valid"][()], h5["support"][()],
                               hemisphere, json.loads(h5["fit"].attrs["json"]),
                               json.loads(h5["provenance"].attrs["json"]))
        except KeyError as error:
            raise LutError(f"{path}: missing {error.args[0]}") from None
        except IvcError as error:
            raise LutError(f"{path}: {error}") from None
        except (ValueError, TypeError, IndexError, AttributeError, OSError, RuntimeError) as error:
            # numbers that are not, bad JSON, a dataset HDF5 cannot read
            raise LutError(f"{path}: malformed look-up table ({error}); make a new one with `ivc fit`") from None
