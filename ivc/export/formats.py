"""One writer per export format; every write is atomic and refuses to replace a file unless asked.

=====================  =====================================================================
``hdf5``               the canonical table (docs/lut.md), as ``ivc fit`` writes it
``npz``                NumPy arrays: origin, spacing, shape, values, valid, support
``csv``                one row per node in Himberg 2010's order (eq. 105: X slowest, Z fastest)
                       under one plain header row; the grid and units in a JSON sidecar
``vti``                VTK image data for ParaView: the nine components, |G| as % of |f_D|,
                       the position distortion, validity and support; geometry and
                       distortion in one length unit, named in the file's FieldData
``slicer``             the position distortion as a displacement field (NRRD, LPS, mm)
                       that 3D Slicer loads as a grid transform (true -> reported: Slicer
                       must invert it to correct)
``slicer-itk``         the correction (reported -> true) as an ITK HDF5 transform that 3D
                       Slicer loads as its to-parent transform, applied with no inversion
``itk``                the same displacement field as a standard ITK DisplacementFieldTransform
                       (ITK, SimpleITK, ANTs): ``TransformPoint(reported) = corrected``
``vrui``               the grid file of Vrui's ForwardGridCalibrator over the region where the
                       tracker reports the mapped volume, in the tracker's unit, ringed by
                       invalid vertices so Vrui does not extrapolate
=====================  =====================================================================

``unit`` is honoured by every format that can carry it and refused by the others (hdf5: the
canonical table is in metres; slicer, slicer-itk, itk: Slicer and ITK work in millimetres); vrui
requires it. ``spacing`` (m) sets the node spacing of the grids over the reported region
(slicer-itk, itk: default the table's spacing / 8; vrui: / 4).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ivc import __version__, dipole
from ivc.errors import ExportError
from ivc.export import distortion
from ivc.files import atomic_path
from ivc.table.lookup import COMPONENTS, FIELD_UNIT, LookupTable
from ivc.table.lookup import write as write_hdf5
from ivc.units import LENGTH_UNITS

#: units each format can be written in (None: any of LENGTH_UNITS), and the default
UNITS = {"hdf5": (("m",), "m"), "npz": (None, "m"), "csv": (None, "m"), "vti": (None, "m"),
         "slicer": (("mm",), "mm"), "slicer-itk": (("mm",), "mm"), "itk": (("mm",), "mm"), "vrui": (None, None)}
#: formats on a grid over the reported region (they take ``spacing``), and the table's spacing divided by
#: what gives their default (measured on the default scene, docs/export.md: ITK interpolates the field
#: trilinearly, so its nodes are closer; a Vrui grid is text, eight times the vertices would be 50 MB)
REPORTED_GRID_FORMATS = ("slicer-itk", "itk", "vrui")
SUBDIVISION = {"slicer-itk": 8, "itk": 8, "vrui": 4}
#: the ITK transform class 3D Slicer reads as a to-parent (modelling-convention) grid transform; plain ITK
#: does not know it (Slicer registers it), so the same field is also written as ``itk``
SLICER_TO_PARENT_CLASS = "InverseDisplacementFieldTransform_double_3_3"
ITK_CLASS = "DisplacementFieldTransform_double_3_3"
#: the tracker frame is taken as Slicer's RAS (as PLUS and OpenIGTLink tracking do); ITK files are LPS
LPS = np.array([-1.0, -1.0, 1.0])
#: invalid vertices added around a Vrui grid: Vrui clamps a pose outside the grid to the boundary cell and
#: extrapolates its corrections, unless a corner of that cell is invalid
VRUI_MARGIN = 1


def _hdf5(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
    write_hdf5(table, path, overwrite=True)


def _npz(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
    scale = 1.0 / LENGTH_UNITS[unit]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, origin=table.grid.origin * scale, spacing=table.grid.spacing * scale,
                            shape=np.array(table.grid.shape),
                            values=table.values, valid=table.valid, support=table.support,
                            components=np.array(COMPONENTS), hemisphere=table.hemisphere, length_unit=unit,
                            field_unit=FIELD_UNIT, index_order="x slowest, z fastest (Himberg 2010, eq. 105)")


def csv_sidecar(path: str | os.PathLike) -> Path:
    """The JSON file beside a CSV export that holds its grid and units: ``<name>.csv.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def _csv(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
    scale = 1.0 / LENGTH_UNITS[unit]
    g = table.grid
    nodes = g.nodes().reshape(-1, 3) * scale
    meta = {
        "format": "ivc secondary-field look-up table", "ivc_version": __version__, "csv": path.name,
        "length_unit": unit, f"origin_{unit}": (g.origin * scale).tolist(), f"spacing_{unit}": g.spacing * scale,
        "counts": list(g.shape),
        "index_order": "x slowest, z fastest (Himberg 2010, eq. 105): row = i*ny*nz + j*nz + k",
        "hemisphere": table.hemisphere, "field_unit": FIELD_UNIT,
        "components": "G[a, b] = field component a of source coil b, source frame",
        "valid": "1 where data support the node, 0 where the values are filled in and must not be used",
    }
    columns = ["i", "j", "k", f"x_{unit}", f"y_{unit}", f"z_{unit}", "valid", "support", *COMPONENTS]
    i, j, k = np.unravel_index(np.arange(g.size), g.shape)
    rows = np.column_stack([i, j, k, nodes, table.valid.reshape(-1), table.support.reshape(-1),
                            table.values.reshape(-1, 9)])
    formats = ["%d"] * 3 + ["%.9g"] * 3 + ["%d"] * 2 + ["%.12g"] * 9
    sidecar = csv_sidecar(path)
    with atomic_path(path) as tmp, atomic_path(sidecar) as tmp_meta:
        np.savetxt(tmp, rows, fmt=formats, delimiter=",", comments="", header=",".join(columns))
        tmp_meta.write_text(json.dumps(meta, indent=2) + "\n")


def _vtk_string_array(name: str, value: str) -> str:
    codes = " ".join(str(c) for c in value.encode()) + " 0"
    return f'<Array type="String" Name="{name}" NumberOfTuples="1" format="ascii">{codes}</Array>'


def _vti(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
    from pyevtk.hl import imageToVTK

    primary = np.linalg.norm(dipole.field(table.grid.nodes()), axis=(-2, -1))
    secondary = np.linalg.norm(table.values, axis=(-2, -1))
    scale = 1.0 / LENGTH_UNITS[unit]
    shift = distortion.forward(table).displacement * scale
    data = {name: np.ascontiguousarray(table.values[..., a, b]) for name, (a, b) in
            zip(COMPONENTS, np.ndindex(3, 3), strict=True)}
    data["secondary_percent_of_primary"] = 100.0 * secondary / primary
    data[f"position_distortion_{unit}"] = tuple(np.ascontiguousarray(shift[..., a]) for a in range(3))
    data["valid"] = table.valid.astype(np.uint8)
    data["support"] = table.support.astype(np.int32)
    g = table.grid
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.") as tmp:
        # plain floats: pyevtk writes str() of each, and a NumPy 2 scalar prints as "np.float64(...)"
        written = imageToVTK(os.path.join(tmp, "table"), origin=tuple((g.origin * scale).tolist()),
                             spacing=(float(g.spacing * scale),) * 3, pointData=data)
        # the units, as FieldData string arrays ParaView shows in its Information panel; inserted in the XML
        # part before the appended binary data, whose offsets are relative to its own start
        raw = Path(written).read_bytes()
        at = raw.index(b"<Piece")
        fields = "<FieldData>\n" + "\n".join(_vtk_string_array(n, v) for n, v in (
            ("length_unit", unit), ("position_distortion_unit", unit), ("field_unit", FIELD_UNIT),
            ("ivc_version", __version__))) + "\n</FieldData>\n"
        Path(written).write_bytes(raw[:at] + fields.encode() + raw[at:])
        shutil.move(written, path)  # same directory: an atomic rename


def _slicer(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
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


def _simpleitk():
    try:
        import SimpleITK
    except ImportError as e:
        raise ExportError("the slicer-itk and itk formats are written with SimpleITK, which is not installed: "
                          "pip install 'ivc[slicer]' (or pip install SimpleITK)") from e
    return SimpleITK


def _itk_displacement(c: distortion.DistortionGrid) -> np.ndarray:
    """The correction's displacement r − v (nx, ny, nz, 3) in LPS mm; an undefined node holds the map's
    extension or its nearest node's displacement (:meth:`DistortionGrid.filled_displacement`)."""
    return c.filled_displacement() * LPS * 1000.0


def _itk(table: LookupTable, path: Path, unit: str, spacing: float | None = None, slicer: bool = False) -> None:
    sitk = _simpleitk()
    import h5py

    c = distortion.reported_correction(table, spacing or table.grid.spacing / SUBDIVISION["itk"])
    g = c.grid
    # SimpleITK's array order is (z, y, x, component): x fastest
    image = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(_itk_displacement(c), (2, 1, 0, 3))),
                                   isVector=True)
    image.SetOrigin(tuple((g.origin * LPS * 1000.0).tolist()))
    image.SetSpacing((g.spacing * 1000.0,) * 3)
    image.SetDirection(tuple(np.diag(LPS).reshape(-1).tolist()))
    transform = sitk.DisplacementFieldTransform(image)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.") as tmp:
        written = Path(tmp) / "transform.h5"  # ITK picks its HDF5 transform IO by the extension
        try:
            sitk.WriteTransform(transform, str(written))
        except RuntimeError as error:  # SimpleITK says every failure so: a full disk, a folder gone read-only
            reason = next((line.strip() for line in str(error).splitlines()[::-1] if line.strip()), "no reason")
            raise ExportError(f"{path}: SimpleITK could not write the transform (is the disk full, or the folder "
                              f"read-only?); nothing was written. SimpleITK said: {reason}") from None
        with h5py.File(written, "r+") as h5:
            if slicer:
                group = h5["TransformGroup/0"]
                del group["TransformType"]
                group.create_dataset("TransformType", data=np.array([SLICER_TO_PARENT_CLASS.encode()], dtype=object),
                                     dtype=h5py.string_dtype("ascii"))
            meta = h5.create_group("ivc")
            meta.attrs.update({
                "ivc_version": __version__, "length_unit": "mm", "space": "LPS (the tracker frame taken as RAS)",
                "direction": "reported position -> true position (the correction): ITK's TransformPoint of a "
                             "reported position gives the corrected one" + (
                                 "; the class name makes 3D Slicer read it as the to-parent transform, applied "
                                 "with no inversion" if slicer else ""),
                "undefined_nodes": "where the correction is not defined (no unique true position in the mapped "
                                   "volume) a node holds the table's extension of the map just past the mapped "
                                   "volume where its inversion converges there, else the displacement of the "
                                   "nearest node that has one; /ivc/valid is 0 at those nodes, and points whose "
                                   "cell touches one are not corrected reliably",
                "orientation": "not in a displacement field: use ivc correct, or the vrui export, for attitudes",
                "tracker_solver": str(table.fit.get("tracker_solver", "closed-form")),
            })
            meta.create_dataset("valid", data=np.ascontiguousarray(np.transpose(c.valid, (2, 1, 0))).astype(np.uint8))
            meta["valid"].attrs["axes"] = "(z, y, x): x fastest, as the displacement field's parameters"
        shutil.move(str(written), path)  # same directory: an atomic rename


def _slicer_itk(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
    _itk(table, path, unit, spacing, slicer=True)


def _vrui(table: LookupTable, path: Path, unit: str, spacing: float | None = None) -> None:
    scale = 1.0 / LENGTH_UNITS[unit]
    c = distortion.reported_correction(table, spacing or table.grid.spacing / SUBDIVISION["vrui"])
    # Vrui corrects a raw pose P by C·P with C = (offset, R), offset = (file translation − vertex): so for
    # P at vertex v to land on the true position t, the file's translation is t − R v + v.
    v = c.source
    t = np.where(c.valid[..., None], c.target, v)
    turn = np.where(c.valid[..., None, None], c.turn, np.eye(3))
    translation = (t - np.einsum("...ij,...j->...i", turn, v) + v) * scale
    rv = c.rotation_vector
    angle = np.linalg.norm(rv, axis=-1)
    axis = np.where(angle[..., None] > 0, rv / np.where(angle > 0, angle, 1.0)[..., None], [1.0, 0.0, 0.0])
    g = c.grid
    m = VRUI_MARGIN
    shape = tuple(n + 2 * m for n in g.shape)
    lines = [" ".join(str(n) for n in shape), " ".join(f"{x:.9g}" for x in (g.origin - m * g.spacing) * scale),
             " ".join(f"{g.spacing * scale:.9g}" for _ in range(3))]
    for padded in np.ndindex(shape):
        idx = tuple(i - m for i in padded)
        inside = all(0 <= i < n for i, n in zip(idx, g.shape, strict=True))
        if inside and c.valid[idx]:
            tx, ty, tz = translation[idx]
            ax, ay, az = axis[idx]
            lines.append(f"V {{({tx:.9g}, {ty:.9g}, {tz:.9g}), {{({ax:.9g}, {ay:.9g}, {az:.9g}), {angle[idx]:.9g}}}}}")
        else:
            lines.append("I")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


FORMATS: dict[str, tuple[Callable[..., None], str, str]] = {
    "hdf5": (_hdf5, ".h5", "the canonical table (ivc's own format)"),
    "npz": (_npz, ".npz", "NumPy arrays"),
    "csv": (_csv, ".csv", "one row per node, the order of Himberg 2010's eq. 105, under a plain header row; grid "
            "and units in FILE.csv.json"),
    "vti": (_vti, ".vti", "VTK image data for ParaView"),
    "slicer": (_slicer, ".nrrd", "the distortion (true -> reported) as a displacement field (LPS, mm) for 3D "
               "Slicer, which inverts it to correct"),
    "slicer-itk": (_slicer_itk, ".h5", "the correction (reported -> true) as an ITK HDF5 transform (LPS, mm) that 3D "
                   "Slicer applies as to-parent with no inversion; needs SimpleITK"),
    "itk": (_itk, ".h5", "the same correction as a standard ITK DisplacementFieldTransform (SimpleITK, ITK, ANTs: "
            "TransformPoint(reported) = corrected); needs SimpleITK"),
    "vrui": (_vrui, ".grid", "Vrui ForwardGridCalibrator grid over the reported region, in the length unit of the "
                             "tracker driver, ringed by invalid vertices"),
}


def export(table: LookupTable, fmt: str, path: str | os.PathLike, *, unit: str | None = None,
           overwrite: bool = False, spacing: float | None = None) -> Path:
    """Write ``table`` as ``fmt`` (a key of :data:`FORMATS`) to ``path``; returns the path written.

    ``unit``: length unit of the file (m, cm, mm, in; default: the format's, :data:`UNITS`). hdf5 is in
    metres, slicer, slicer-itk and itk in millimetres only; vrui needs it (Vrui corrects in the tracker
    driver's unit: inches for Polhemus). ``spacing`` (m): node spacing of the grid over the reported
    region (:data:`REPORTED_GRID_FORMATS`; default the table's divided by :data:`SUBDIVISION`), refused
    for the other formats.
    """
    unit = resolve_unit(fmt, unit)
    if spacing is not None and fmt not in REPORTED_GRID_FORMATS:
        raise ExportError(f"{fmt} is written on the table's own grid; a spacing applies to "
                          f"{', '.join(REPORTED_GRID_FORMATS)} only")
    path = Path(path)
    written = [path, csv_sidecar(path)] if fmt == "csv" else [path]
    for p in written:
        if p.exists() and not overwrite:
            raise FileExistsError(f"{p} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    FORMATS[fmt][0](table, path, unit, spacing)
    return path


def resolve_unit(fmt: str, unit: str | None) -> str:
    """The length unit ``fmt`` is written in for the asked ``unit`` (None: the format's default), or an
    :class:`ExportError` saying why it cannot be."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    allowed, default = UNITS[fmt]
    unit = default if unit is None else unit
    if unit is None:
        raise ExportError("vrui: give the length unit of the tracker driver's poses (unit=in for Vrui's Polhemus "
                          "drivers, which report inches; m, cm or mm for others): Vrui applies the grid in that "
                          "unit and a mismatch corrects nothing")
    if unit not in LENGTH_UNITS:
        raise ExportError(f"unknown length unit {unit!r}; choose one of {', '.join(LENGTH_UNITS)}")
    if allowed is not None and unit not in allowed:
        why = "the canonical table" if fmt == "hdf5" else "3D Slicer and ITK work in millimetres"
        raise ExportError(f"{fmt} files are in {allowed[0]} only ({why}); drop unit={unit}")
    return unit

