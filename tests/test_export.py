"""Every export format read back by a reader that is not ivc's, and the pose-domain distortion it rests on."""

import csv
import re

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from ivc import dipole, rotations
from ivc.cli import cli
from ivc.dipole.pose import closed_form_pose
from ivc.export import FORMATS, ExportError, distortion, export
from ivc.lut import Grid, LookupTable
from ivc.lut import write as write_lut
from ivc.lut.table import COMPONENTS
from tests.helpers import CENTRE, quadratic_field

MM = 1000.0


@pytest.fixture(scope="module")
def table():
    """A smooth secondary field (a few mm of distortion) on a 7x6x5 grid with one unmapped corner."""
    grid = Grid(CENTRE - [0.15, 0.12, 0.1], 0.05, (7, 6, 5))
    values = 0.1 * quadratic_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3)
    valid = np.ones(grid.shape, bool)
    valid[0, 0, 0] = False
    support = np.arange(grid.size).reshape(grid.shape) % 50 + 20
    return LookupTable(grid, values, valid, support, fit={"method": "test"})


def test_the_distortion_depends_on_position_only(table, rng):
    """Any attitude T: the reported position is the forward map's and the reported attitude is C·T."""
    d = distortion.forward(table)
    idx = tuple(np.array([[3, 2, 1], [6, 5, 4], [1, 4, 2]]).T)
    T = rotations.to_matrix(rotations.random(3, rng))
    S = np.einsum("nji,njk->nik", T, dipole.field(d.source[idx]) + table.values[idx])  # Tᵀ F
    position, turn = closed_form_pose(S, table.hemisphere)
    assert np.allclose(position, d.target[idx], atol=1e-12)
    assert np.allclose(turn, d.turn[idx] @ T, atol=1e-9)
    assert 1.0 < np.nanmax(np.linalg.norm(d.displacement, axis=-1)) * MM < 50.0  # a real, mm-scale distortion


def test_correction_inverts_the_forward_map(table):
    c = distortion.correction(table)
    assert c.valid.sum() > 0.5 * table.grid.size
    position, turn, mapped = distortion.reported(table.field(), c.target[c.valid], table.hemisphere)
    assert np.abs(position - c.source[c.valid]).max() < 1e-8
    assert np.allclose(turn @ c.turn[c.valid], np.eye(3), atol=1e-9)
    assert mapped.all()


def test_hdf5_read_by_h5py(table, tmp_path):
    path = export(table, "hdf5", tmp_path / "t.h5")
    with h5py.File(path, "r") as h5:
        assert np.array_equal(h5["values"][()], table.values)
        assert np.array_equal(h5["valid"][()], table.valid)
        assert np.array_equal(h5["support"][()], table.support)
        assert np.allclose(h5["grid"].attrs["origin"], table.grid.origin)
        assert h5["grid"].attrs["spacing"] == table.grid.spacing


def test_npz_read_by_numpy(table, tmp_path):
    data = np.load(export(table, "npz", tmp_path / "t.npz"))
    assert np.array_equal(data["values"], table.values)
    assert np.array_equal(data["valid"], table.valid)
    assert tuple(data["shape"]) == table.grid.shape
    assert list(data["components"]) == list(COMPONENTS)


def test_csv_read_by_the_csv_module_in_eq105_order(table, tmp_path):
    path = export(table, "csv", tmp_path / "t.csv", unit="mm")
    lines = path.read_text().splitlines()
    header = {k.strip(): v.strip() for k, v in (line[2:].split(":", 1) for line in lines if line.startswith("# ")
                                                 and ":" in line and "," not in line.split(":", 1)[0])}
    assert [int(n) for n in header["counts"].split()] == list(table.grid.shape)
    assert np.allclose([float(v) for v in header["origin_mm"].split()], table.grid.origin * MM)
    assert float(header["spacing_mm"]) == pytest.approx(table.grid.spacing * MM)
    columns = lines[[i for i, line in enumerate(lines) if line.startswith("# i,j,k")][0]][2:].split(",")
    rows = list(csv.DictReader((line for line in lines if not line.startswith("#")), fieldnames=columns))
    assert len(rows) == table.grid.size
    nx, ny, nz = table.grid.shape
    for n in (0, 1, nz, ny * nz, table.grid.size - 1):  # row = i*ny*nz + j*nz + k
        i, j, k = int(rows[n]["i"]), int(rows[n]["j"]), int(rows[n]["k"])
        assert n == i * ny * nz + j * nz + k
        assert np.allclose([float(rows[n][c]) for c in COMPONENTS], table.values[i, j, k].ravel(), rtol=1e-11)
        assert np.allclose([float(rows[n][c]) for c in ("x_mm", "y_mm", "z_mm")], table.grid.nodes()[i, j, k] * MM)
        assert int(rows[n]["valid"]) == table.valid[i, j, k]


def _vtk_array(image, name):
    from vtk.util.numpy_support import vtk_to_numpy

    nx, ny, nz = image.GetDimensions()
    a = vtk_to_numpy(image.GetPointData().GetArray(name))
    return a.reshape(nz, ny, nx, *a.shape[1:]).transpose(2, 1, 0, *range(3, a.ndim + 2))  # VTK: x fastest


def test_vti_read_by_vtk(table, tmp_path):
    vtk = pytest.importorskip("vtk")
    reader = vtk.vtkXMLImageDataReader()
    reader.SetFileName(str(export(table, "vti", tmp_path / "t.vti")))
    reader.Update()
    image = reader.GetOutput()
    assert image.GetDimensions() == table.grid.shape
    assert np.allclose(image.GetOrigin(), table.grid.origin)
    assert np.allclose(image.GetSpacing(), table.grid.spacing)
    for name, (a, b) in zip(COMPONENTS, np.ndindex(3, 3), strict=True):
        assert np.array_equal(_vtk_array(image, name), table.values[..., a, b])
    assert np.array_equal(_vtk_array(image, "valid").astype(bool), table.valid)
    primary = np.linalg.norm(dipole.field(table.grid.nodes()), axis=(-2, -1))
    assert np.allclose(_vtk_array(image, "secondary_percent_of_primary"),
                       100 * np.linalg.norm(table.values, axis=(-2, -1)) / primary)
    assert np.allclose(_vtk_array(image, "position_distortion_mm"), distortion.forward(table).displacement * MM)


def test_slicer_displacement_field_read_by_simpleitk(table, tmp_path):
    """ITK maps a true point (LPS, mm) to where the tracker reports it, at every mapped node."""
    sitk = pytest.importorskip("SimpleITK")
    image = sitk.ReadImage(str(export(table, "slicer", tmp_path / "t.nrrd")), sitk.sitkVectorFloat64)
    transform = sitk.DisplacementFieldTransform(image)
    lps = np.array([-1.0, -1.0, 1.0])
    d = distortion.forward(table)
    for idx in zip(*np.nonzero(d.valid), strict=True):
        mapped = transform.TransformPoint(tuple(d.source[idx] * lps * MM))
        assert np.allclose(mapped, d.target[idx] * lps * MM, atol=1e-9)
    assert transform.TransformPoint(tuple(d.source[0, 0, 0] * lps * MM)) == pytest.approx(
        tuple(d.source[0, 0, 0] * lps * MM))  # unmapped: no displacement


class _Istream:
    """The C++ ``istream >>`` extraction the Vrui reader uses: a char skips whitespace and takes one
    character; a number skips whitespace and takes the longest numeric prefix."""

    _number = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")

    def __init__(self, text):
        self.text, self.at = text, 0

    def _skip(self):
        while self.text[self.at].isspace():
            self.at += 1

    def char(self):
        self._skip()
        self.at += 1
        return self.text[self.at - 1]

    def number(self):
        self._skip()
        match = self._number.match(self.text, self.at)
        self.at = match.end()
        return float(match.group())


def _read_vrui(text):
    """ForwardGridCalibrator's constructor: grid header, then per vertex (z fastest) a flag and a transform."""
    s = _Istream(text)
    size = [int(s.number()) for _ in range(3)]
    base = np.array([s.number() for _ in range(3)])
    cell = np.array([s.number() for _ in range(3)])
    offset, rotvec, valid = np.zeros((*size, 3)), np.zeros((*size, 3)), np.zeros(size, bool)
    for idx in np.ndindex(*size):
        if s.char() != "V":
            continue
        s.char()
        t = [(s.char(), s.number())[1] for _ in range(3)]
        s.char(), s.char(), s.char()
        axis = [(s.char(), s.number())[1] for _ in range(3)]
        s.char(), s.char()
        angle = s.number()
        s.char(), s.char()
        offset[idx] = np.array(t) - (base + np.array(idx) * cell)
        rotvec[idx] = np.array(axis) / np.linalg.norm(axis) * angle
        valid[idx] = True
    return base, cell, offset, rotvec, valid


def test_vrui_grid_read_as_vrui_does_corrects_at_the_vertices(table, tmp_path):
    base, cell, offset, rotvec, valid = _read_vrui(export(table, "vrui", tmp_path / "t.grid").read_text())
    c = distortion.correction(table)
    assert np.array_equal(valid, c.valid)
    assert np.allclose(base, table.grid.origin) and np.allclose(cell, table.grid.spacing)
    # Vrui applies (offset, R) on the left: p' = offset + R p, T' = R T
    R = rotations.to_matrix(rotations.from_rotvec(rotvec[valid]))
    vertices = table.grid.nodes()[valid]
    corrected = offset[valid] + np.einsum("nij,nj->ni", R, vertices)
    assert np.abs(corrected - c.target[valid]).max() < 1e-8
    assert np.allclose(R, c.turn[valid], atol=1e-8)


def test_cli_export_every_format_and_refuse_to_overwrite(table, tmp_path):
    lut_path = tmp_path / "map.h5"
    write_lut(table, lut_path)
    runner = CliRunner()
    for fmt, (_, ext, _) in FORMATS.items():
        if fmt == "hdf5":
            continue
        result = runner.invoke(cli, ["export", str(lut_path), "--format", fmt])
        assert result.exit_code == 0, result.output
        assert (tmp_path / f"map{ext}").stat().st_size > 0
    again = runner.invoke(cli, ["export", str(lut_path), "--format", "csv"])
    assert again.exit_code != 0 and "exists" in again.output
    same = runner.invoke(cli, ["export", str(lut_path), "--format", "hdf5", "-o", str(lut_path), "--force"])
    assert same.exit_code != 0 and "must not be the table" in same.output
    with pytest.raises(ExportError, match="unknown export format"):
        export(table, "stl", tmp_path / "x.stl")
