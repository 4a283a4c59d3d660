"""One writer per export format; every write is atomic and refuses to replace a file unless asked.

=====================  =====================================================================
``hdf5``               the canonical table (docs/lut.md), as ``ivc fit`` writes it
``npz``                NumPy arrays: origin, spacing, shape, values, valid, support
``csv``                one row per node in the seed's order (eq. 105: X slowest, Z fastest)
                       under a ``#`` header that a firmware loader can parse
``vti``                VTK image data for ParaView: the nine components, |G| as % of |f_D|,
                       the position distortion (mm), validity and support
``slicer``             the position distortion as a displacement field (NRRD, LPS, mm)
                       that 3D Slicer loads as a grid transform
``vrui``               the grid file of Vrui's ForwardGridCalibrator
=====================  =====================================================================
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ivc import __version__, dipole
from ivc.errors import ExportError
from ivc.export import distortion
from ivc.lut.table import COMPONENTS, LookupTable
from ivc.lut.table import write as write_hdf5
from ivc.session import atomic_path
from ivc.units import LENGTH_UNITS

FIELD_UNIT = "normalised dipole units (f_D of MATH.md §2)"


def _hdf5(table: LookupTable, path: Path, unit: str) -> None:
    write_hdf5(table, path, overwrite=True)


def _npz(table: LookupTable, path: Path, unit: str) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, origin=table.grid.origin, spacing=table.grid.spacing, shape=np.array(table.grid.shape),
                            values=table.values, valid=table.valid, support=table.support,
                            components=np.array(COMPONENTS), hemisphere=table.hemisphere, length_unit="m",
                            field_unit=FIELD_UNIT, index_order="x slowest, z fastest (seed eq. 105)")


def _csv(table: LookupTable, path: Path, unit: str) -> None:
    scale = 1.0 / LENGTH_UNITS[unit]
    g = table.grid
    nodes = g.nodes().reshape(-1, 3) * scale
    header = [
        "ivc secondary-field look-up table",
        f"ivc_version: {__version__}",
        f"origin_{unit}: {' '.join(f'{v:.9g}' for v in g.origin * scale)}",
        f"spacing_{unit}: {g.spacing * scale:.9g}",
        f"counts: {' '.join(str(n) for n in g.shape)}",
        "index_order: x slowest, z fastest (seed eq. 105): row = i*ny*nz + j*nz + k",
        f"hemisphere: {table.hemisphere}",
        f"field_unit: {FIELD_UNIT}; G[a, b] = field component a of source coil b, source frame",
        "valid: 1 where data support the node, 0 where the values are filled in and must not be used",
    ]
    columns = ["i", "j", "k", f"x_{unit}", f"y_{unit}", f"z_{unit}", "valid", "support", *COMPONENTS]
    i, j, k = np.unravel_index(np.arange(g.size), g.shape)
    rows = np.column_stack([i, j, k, nodes, table.valid.reshape(-1), table.support.reshape(-1),
                            table.values.reshape(-1, 9)])
    formats = ["%d"] * 3 + ["%.9g"] * 3 + ["%d"] * 2 + ["%.12g"] * 9
    with atomic_path(path) as tmp:
        np.savetxt(tmp, rows, fmt=formats, delimiter=",", comments="# ",
                   header="\n".join(header) + "\n" + ",".join(columns))


def _vti(table: LookupTable, path: Path, unit: str) -> None:
    from pyevtk.hl import imageToVTK

    primary = np.linalg.norm(dipole.field(table.grid.nodes()), axis=(-2, -1))
    secondary = np.linalg.norm(table.values, axis=(-2, -1))
    shift = distortion.forward(table).displacement * 1000.0
    data = {name: np.ascontiguousarray(table.values[..., a, b]) for name, (a, b) in
            zip(COMPONENTS, np.ndindex(3, 3), strict=True)}
    data["secondary_percent_of_primary"] = 100.0 * secondary / primary
    data["position_distortion_mm"] = tuple(np.ascontiguousarray(shift[..., a]) for a in range(3))
    data["valid"] = table.valid.astype(np.uint8)
    data["support"] = table.support.astype(np.int32)
    g = table.grid
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.") as tmp:
        # plain floats: pyevtk writes str() of each, and a NumPy 2 scalar prints as "np.float64(...)"
        written = imageToVTK(os.path.join(tmp, "table"), origin=tuple(g.origin.tolist()),
                             spacing=(float(g.spacing),) * 3, pointData=data)
        shutil.move(written, path)  # same directory: an atomic rename


def _slicer(table: LookupTable, path: Path, unit: str) -> None:
    import nrrd

    d = distortion.forward(table)
    lps = np.array([-1.0, -1.0, 1.0])  # the tracker frame is taken as RAS; files are LPS
    shift = d.displacement * lps * 1000.0  # (nx, ny, nz, 3) mm
    g = table.grid
    header = {
        "type": "double", "dimension": 4, "space": "left-posterior-superior",
        "kinds": ["vector", "domain", "domain", "domain"],
        "space directions": np.vstack([np.full(3, np.nan), np.diag(lps * g.spacing * 1000.0)]),
        "space origin": g.origin * lps * 1000.0, "endian": "little", "encoding": "gzip",
        "ivc_direction": "true position -> position the tracker reports (ITK resampling convention: fixed = true "
                         "room, moving = tracker); in 3D Slicer its to-parent direction corrects",
        "ivc_invalid_nodes": "zero displacement (no data)",
        "ivc_version": __version__,
    }
    data = np.moveaxis(shift, -1, 0)  # (3, nx, ny, nz): NRRD's fastest axis first, index_order "F"
    with atomic_path(path) as tmp:
        nrrd.write(str(tmp), np.asfortranarray(data), header, index_order="F")


def _vrui(table: LookupTable, path: Path, unit: str) -> None:
    scale = 1.0 / LENGTH_UNITS[unit]
    c = distortion.correction(table)
    # Vrui corrects a raw pose P by C·P with C = (offset, R), offset = (file translation − vertex): so for
    # P at vertex v to land on the true position t, the file's translation is t − R v + v.
    v = c.source
    t = np.where(c.valid[..., None], c.target, v)
    turn = np.where(c.valid[..., None, None], c.turn, np.eye(3))
    translation = (t - np.einsum("...ij,...j->...i", turn, v) + v) * scale
    rv = c.rotation_vector
    angle = np.linalg.norm(rv, axis=-1)
    axis = np.where(angle[..., None] > 0, rv / np.where(angle > 0, angle, 1.0)[..., None], [1.0, 0.0, 0.0])
    g = table.grid
    lines = [" ".join(str(n) for n in g.shape), " ".join(f"{x:.9g}" for x in g.origin * scale),
             " ".join(f"{g.spacing * scale:.9g}" for _ in range(3))]
    for idx in np.ndindex(g.shape):
        if c.valid[idx]:
            tx, ty, tz = translation[idx]
            ax, ay, az = axis[idx]
            lines.append(f"V {{({tx:.9g}, {ty:.9g}, {tz:.9g}), {{({ax:.9g}, {ay:.9g}, {az:.9g}), {angle[idx]:.9g}}}}}")
        else:
            lines.append("I")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


FORMATS: dict[str, tuple[Callable[[LookupTable, Path, str], None], str, str]] = {
    "hdf5": (_hdf5, ".h5", "the canonical table (ivc's own format)"),
    "npz": (_npz, ".npz", "NumPy arrays"),
    "csv": (_csv, ".csv", "one row per node, seed eq. 105 order, header with grid and units"),
    "vti": (_vti, ".vti", "VTK image data for ParaView"),
    "slicer": (_slicer, ".nrrd", "displacement-field transform (LPS, mm) for 3D Slicer"),
    "vrui": (_vrui, ".grid", "Vrui ForwardGridCalibrator grid"),
}


def export(table: LookupTable, fmt: str, path: str | os.PathLike, *, unit: str = "m", overwrite: bool = False) -> Path:
    """Write ``table`` as ``fmt`` (a key of :data:`FORMATS`) to ``path``; returns the path written.

    ``unit``: length unit of the csv and vrui files (m, cm, mm, in); the others have fixed units.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if unit not in LENGTH_UNITS:
        raise ExportError(f"unknown length unit {unit!r}; choose one of {', '.join(LENGTH_UNITS)}")
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass --force to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    FORMATS[fmt][0](table, path, unit)
    return path

