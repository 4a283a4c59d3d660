"""Every export format read back by a reader that is not ivc's, and the pose-domain distortion it rests on."""

import csv
import json
import re

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from ivc import dipole, rotations
from ivc.cli import cli
from ivc.correct.reported import PoseCorrector
from ivc.dipole.pose import closed_form_pose
from ivc.export import FORMATS, SLICER_TO_PARENT_CLASS, VRUI_MARGIN, ExportError, csv_sidecar, distortion, export
from ivc.lut import Grid, LookupTable
from ivc.lut import write as write_lut
from ivc.table.lookup import COMPONENTS
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
    meta = json.loads(csv_sidecar(path).read_text())
    assert meta["counts"] == list(table.grid.shape) and meta["length_unit"] == "mm"
    assert np.allclose(meta["origin_mm"], table.grid.origin * MM)
    assert meta["spacing_mm"] == pytest.approx(table.grid.spacing * MM)
    assert "f_D(r) = (3 r r^T" in meta["field_unit"] and "MATH" not in meta["field_unit"]
    rows = list(csv.DictReader(lines))  # a plain header row, nothing else
    assert len(rows) == table.grid.size
    nx, ny, nz = table.grid.shape
    for n in (0, 1, nz, ny * nz, table.grid.size - 1):  # row = i*ny*nz + j*nz + k
        i, j, k = int(rows[n]["i"]), int(rows[n]["j"]), int(rows[n]["k"])
        assert n == i * ny * nz + j * nz + k
        assert np.allclose([float(rows[n][c]) for c in COMPONENTS], table.values[i, j, k].ravel(), rtol=1e-11)
        assert np.allclose([float(rows[n][c]) for c in ("x_mm", "y_mm", "z_mm")], table.grid.nodes()[i, j, k] * MM)
        assert int(rows[n]["valid"]) == table.valid[i, j, k]


def test_csv_read_by_pandas_and_numpy_with_their_defaults(table, tmp_path):
    pd = pytest.importorskip("pandas")
    path = export(table, "csv", tmp_path / "t.csv")
    frame = pd.read_csv(path)
    assert len(frame) == table.grid.size and list(frame.columns[:6]) == ["i", "j", "k", "x_m", "y_m", "z_m"]
    np.testing.assert_allclose(frame[list(COMPONENTS)].to_numpy(), table.values.reshape(-1, 9), rtol=1e-11)
    array = np.genfromtxt(path, names=True, delimiter=",")
    assert array.shape == (table.grid.size,) and array.dtype.names[:3] == ("i", "j", "k")
    np.testing.assert_array_equal(array["valid"].astype(bool), table.valid.reshape(-1))


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
    assert np.allclose(_vtk_array(image, "position_distortion_m"), distortion.forward(table).displacement)
    fields = image.GetFieldData()
    assert fields.GetAbstractArray("length_unit").GetValue(0) == "m"
    assert "f_D(r)" in fields.GetAbstractArray("field_unit").GetValue(0)


def test_vti_geometry_and_distortion_share_the_asked_unit(table, tmp_path):
    vtk = pytest.importorskip("vtk")
    reader = vtk.vtkXMLImageDataReader()
    reader.SetFileName(str(export(table, "vti", tmp_path / "t.vti", unit="mm")))
    reader.Update()
    image = reader.GetOutput()
    assert np.allclose(image.GetOrigin(), table.grid.origin * MM)
    assert np.allclose(image.GetSpacing(), table.grid.spacing * MM)
    shift = _vtk_array(image, "position_distortion_mm")
    assert np.allclose(shift, distortion.forward(table).displacement * MM)
    assert image.GetFieldData().GetAbstractArray("length_unit").GetValue(0) == "mm"
    # Warp By Vector: node + distortion, both in the file's unit, is where the tracker reports the node
    d = distortion.forward(table)
    assert np.allclose((table.grid.nodes() * MM + shift)[d.valid], d.target[d.valid] * MM)
    for name, (a, b) in zip(COMPONENTS, np.ndindex(3, 3), strict=True):  # the field values are unitless
        assert np.array_equal(_vtk_array(image, name), table.values[..., a, b])


def test_unit_is_honoured_or_refused_by_every_format(table, tmp_path):
    with np.load(export(table, "npz", tmp_path / "t.npz", unit="mm")) as data:
        assert str(data["length_unit"]) == "mm" and np.allclose(data["origin"], table.grid.origin * MM)
        assert float(data["spacing"]) == pytest.approx(table.grid.spacing * MM)
    with pytest.raises(ExportError, match="hdf5 files are in m only"):
        export(table, "hdf5", tmp_path / "t.h5", unit="mm")
    with pytest.raises(ExportError, match="slicer files are in mm only"):
        export(table, "slicer", tmp_path / "t.nrrd", unit="m")
    export(table, "slicer", tmp_path / "t.nrrd", unit="mm")
    with pytest.raises(ExportError, match="unit=in for Vrui's Polhemus"):
        export(table, "vrui", tmp_path / "t.grid")
    assert not (tmp_path / "t.grid").exists() and not (tmp_path / "t.h5").exists()
    lut_path = tmp_path / "map.h5"
    write_lut(table, lut_path)
    refused = CliRunner().invoke(cli, ["export", str(lut_path), "--format", "slicer", "--unit", "in"])
    assert refused.exit_code == 1 and "mm only" in refused.output and "Traceback" not in refused.output


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


def _vrui_apply(base, cell, offset, rotvec, valid, p):
    """ForwardGridCalibrator's lookup: the cell index clamped to the grid (so a point outside it is
    extrapolated from the boundary cell), raw pose untouched if any corner is invalid, else trilinear."""
    size = np.array(valid.shape)
    x = (p - base) / cell
    index = np.clip(np.floor(x).astype(int), 0, size - 2)
    w = x - index
    corners = [tuple(index + np.array(c)) for c in np.ndindex(2, 2, 2)]
    if not all(valid[c] for c in corners):
        return p
    weights = [np.prod([w[a] if c[a] else 1 - w[a] for a in range(3)]) for c in np.ndindex(2, 2, 2)]
    o = sum(wt * offset[c] for wt, c in zip(weights, corners, strict=True))
    r = sum(wt * rotvec[c] for wt, c in zip(weights, corners, strict=True))
    return o + rotations.to_matrix(rotations.from_rotvec(r)) @ p


@pytest.fixture(scope="module")
def reported_grid(table):
    """The correction on the default grid over the reported region (what slicer-itk, itk and vrui hold)."""
    return distortion.reported_correction(table)


def _reported_check_poses(table, rng, n=300):
    """True poses inside the mapped volume, what the tracker reports for them, and which ivc trusts."""
    g = table.grid
    r = g.origin + g.spacing * (1 + rng.uniform(0, np.array(g.shape) - 3, (n, 3)))
    r = r[table.field().evaluate(r)[2]]
    T = rotations.to_matrix(rotations.random(len(r), rng))
    v, C, _ = distortion.reported(table.field(), r, table.hemisphere)
    Q = C @ T
    out = PoseCorrector(table).batch(v, rotations.from_matrix(Q))
    return r, T, v, Q, out


def test_reported_region_covers_the_reported_positions(table, reported_grid, rng):
    """The grid spans where the tracker reports the mapped volume, and every defined node is the pose-only
    correction of a pose reported there."""
    c = reported_grid
    r, T, v, Q, out = _reported_check_poses(table, rng)
    trusted = out.flags == 0
    assert trusted.mean() > 0.95
    assert c.grid.contains(v).all()
    nodes = c.source[c.valid]
    check = PoseCorrector(table).batch(nodes, np.tile([1.0, 0.0, 0.0, 0.0], (len(nodes), 1)))
    assert np.array_equal(check.position, c.target[c.valid])
    assert np.allclose(rotations.to_matrix(check.quaternion), c.turn[c.valid], atol=1e-12)
    position, turn, mapped = distortion.reported(table.field(), c.target[c.valid], table.hemisphere)
    assert np.abs(position - nodes).max() < 1e-9 and mapped.all()
    assert np.allclose(turn @ c.turn[c.valid], np.eye(3), atol=1e-9)


def test_itk_transform_read_by_simpleitk_moves_reported_positions_to_the_corrected_ones(table, rng, tmp_path):
    """SimpleITK's TransformPoint of a reported position (LPS, mm) gives ivc's pose-only correction of it."""
    sitk = pytest.importorskip("SimpleITK")
    path = export(table, "itk", tmp_path / "t_itk.h5", spacing=0.01)
    transform = sitk.ReadTransform(str(path))
    assert transform.GetName() == "DisplacementFieldTransform"
    lps = np.array([-1.0, -1.0, 1.0])
    r, T, v, Q, out = _reported_check_poses(table, rng)
    ok = out.flags == 0
    moved = np.array([transform.TransformPoint(tuple(p)) for p in v[ok] * lps * MM]) * lps / MM
    gap = np.linalg.norm(moved - out.position[ok], axis=1) * MM
    assert np.median(gap) < 0.01 and gap.max() < 0.1  # trilinear between 10 mm nodes of a smooth field
    assert np.linalg.norm(out.position[ok] - r[ok], axis=1).max() < 1e-8  # and ivc's correction is the truth
    # at the nodes, exactly the correction
    c = distortion.reported_correction(table, spacing=0.01)
    nodes = c.source[c.valid][::37]
    at = np.array([transform.TransformPoint(tuple(p)) for p in nodes * lps * MM]) * lps / MM
    assert np.abs(at - c.target[c.valid][::37]).max() < 1e-12
    # undefined nodes hold the map's extension past the mapped volume (or their nearest node's), never zero
    with h5py.File(path, "r") as h5:
        valid = np.transpose(h5["/ivc/valid"][()], (2, 1, 0)).astype(bool)
        assert "extension of the map" in h5["ivc"].attrs["undefined_nodes"]
    assert np.array_equal(valid, c.valid) and not valid.all()
    filled = c.filled_displacement()
    assert np.all(np.isfinite(filled))
    extended = ~c.valid & np.all(np.isfinite(c.extension), axis=-1)
    assert extended.any()
    assert np.allclose(filled[extended], (c.extension - c.source)[extended], atol=1e-15)
    for idx in map(tuple, np.argwhere(~c.valid)[::11]):
        shift = np.array(transform.TransformPoint(tuple(c.source[idx] * lps * MM))) * lps / MM - c.source[idx]
        assert np.allclose(shift, filled[idx], atol=1e-12) and np.linalg.norm(shift) > 0
    # outside the grid, ITK moves nothing
    far = tuple((c.grid.origin - 0.1) * lps * MM)
    assert transform.TransformPoint(far) == pytest.approx(far)


def test_slicer_itk_is_the_itk_field_under_the_class_slicer_reads_as_to_parent(table, tmp_path):
    """3D Slicer reads InverseDisplacementFieldTransform as a to-parent grid transform (applied to points as
    stored, no inversion); plain ITK does not know that class, which is why itk is written too."""
    sitk = pytest.importorskip("SimpleITK")
    slicer = export(table, "slicer-itk", tmp_path / "t_slicer.h5")
    plain = export(table, "itk", tmp_path / "t_itk.h5")
    with h5py.File(slicer, "r") as a, h5py.File(plain, "r") as b:
        assert a["TransformGroup/0/TransformType"][0].decode() == SLICER_TO_PARENT_CLASS
        assert b["TransformGroup/0/TransformType"][0].decode() == "DisplacementFieldTransform_double_3_3"
        for name in ("TransformParameters", "TransformFixedParameters"):
            assert np.array_equal(a["TransformGroup/0/" + name][()], b["TransformGroup/0/" + name][()])
        assert np.array_equal(a["/ivc/valid"][()], b["/ivc/valid"][()])
        assert "to-parent" in a["ivc"].attrs["direction"]
    with pytest.raises(RuntimeError, match="InverseDisplacementFieldTransform"):
        sitk.ReadTransform(str(slicer))


def test_itk_exports_need_simpleitk_and_say_so(table, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "SimpleITK", None)  # import SimpleITK now raises ImportError
    for fmt in ("slicer-itk", "itk"):
        with pytest.raises(ExportError, match=r"pip install 'ivc\[slicer\]'"):
            export(table, fmt, tmp_path / f"{fmt}.h5")
        assert not (tmp_path / f"{fmt}.h5").exists()
    with pytest.raises(ExportError, match="spacing applies to"):
        export(table, "vti", tmp_path / "t.vti", spacing=0.01)


def test_vrui_grid_read_as_vrui_does_corrects_at_the_vertices(table, reported_grid, tmp_path):
    base, cell, offset, rotvec, valid = _read_vrui(export(table, "vrui", tmp_path / "t.grid", unit="m").read_text())
    c = reported_grid
    m = VRUI_MARGIN
    inner = (slice(m, -m),) * 3
    assert not valid[0].any() and not valid[-1].any() and not valid[:, 0].any() and not valid[:, :, -1].any()
    assert np.array_equal(valid[inner], c.valid)
    offset, rotvec, valid = offset[inner], rotvec[inner], valid[inner]
    base = base + m * cell
    assert np.allclose(base, c.grid.origin) and np.allclose(cell, c.grid.spacing)
    # Vrui applies (offset, R) on the left: p' = offset + R p, T' = R T
    R = rotations.to_matrix(rotations.from_rotvec(rotvec[valid]))
    vertices = c.grid.nodes()[valid]
    corrected = offset[valid] + np.einsum("nij,nj->ni", R, vertices)
    assert np.abs(corrected - c.target[valid]).max() < 1e-8
    assert np.allclose(R, c.turn[valid], atol=1e-8)


def test_vrui_grid_covers_the_reported_poses_and_corrects_them(table, rng, tmp_path):
    """Vrui's own lookup at the reported check poses lands on ivc's corrections (its grid is in reported
    coordinates and spans where they are reported)."""
    base, cell, offset, rotvec, valid = _read_vrui(export(table, "vrui", tmp_path / "t.grid", unit="mm",
                                                          spacing=0.01).read_text())
    r, T, v, Q, out = _reported_check_poses(table, rng, 150)
    ok = out.flags == 0
    size = np.array(valid.shape)
    gap, covered = [], 0
    for p, target in zip(v[ok] * MM, out.position[ok] * MM, strict=True):
        index = np.clip(np.floor((p - base) / cell).astype(int), 0, size - 2)
        corners = [tuple(index + np.array(k)) for k in np.ndindex(2, 2, 2)]
        if all(valid[k] for k in corners):
            covered += 1
            gap.append(np.linalg.norm(_vrui_apply(base, cell, offset, rotvec, valid, p) - target))
    assert covered >= 0.95 * ok.sum()
    assert np.median(gap) < 0.02 and np.max(gap) < 0.2  # mm: trilinear between 10 mm vertices


def test_vrui_leaves_poses_outside_the_grid_alone(table, reported_grid, tmp_path):
    grid_file = export(table, "vrui", tmp_path / "t.grid", unit="mm")
    base, cell, offset, rotvec, valid = _read_vrui(grid_file.read_text())
    g = reported_grid.grid
    centre = (g.origin + g.spacing * (np.array(g.shape) - 1) / 2) * MM
    below = centre - [0, 0, 180.0 + g.spacing * MM * (g.shape[2] - 1) / 2]  # 180 mm below the grid
    assert np.array_equal(_vrui_apply(base, cell, offset, rotvec, valid, below), below)
    inside = centre + 0.3 * g.spacing * MM
    assert not np.allclose(_vrui_apply(base, cell, offset, rotvec, valid, inside), inside)  # still corrects
    assert np.allclose(base, (g.origin - VRUI_MARGIN * g.spacing) * MM) and np.allclose(cell, g.spacing * MM)


@pytest.mark.slow  # every export format through the CLI, end to end
def test_cli_export_every_format_and_refuse_to_overwrite(table, tmp_path):
    lut_path = tmp_path / "map.h5"
    write_lut(table, lut_path)
    runner = CliRunner()
    for fmt, (_, ext, _) in FORMATS.items():
        if fmt == "hdf5":
            continue
        result = runner.invoke(cli, ["export", str(lut_path), "--format", fmt, *(["--unit", "in"] if fmt == "vrui"
                                                                                 else [])])
        assert result.exit_code == 0, result.output
        name = {"slicer-itk": "map_slicer.h5", "itk": "map_itk.h5"}.get(fmt, f"map{ext}")
        assert (tmp_path / name).stat().st_size > 0 and name in result.output
    spaced = runner.invoke(cli, ["export", str(lut_path), "--format", "itk", "--spacing", "20", "-o",
                                 str(tmp_path / "fine.h5")])
    assert spaced.exit_code == 0, spaced.output
    refused = runner.invoke(cli, ["export", str(lut_path), "--format", "csv", "--spacing", "20", "-o",
                                  str(tmp_path / "x.csv")])
    assert refused.exit_code != 0 and "--spacing applies to" in refused.output
    again = runner.invoke(cli, ["export", str(lut_path), "--format", "csv"])
    assert again.exit_code != 0 and "exists" in again.output
    same = runner.invoke(cli, ["export", str(lut_path), "--format", "hdf5", "-o", str(lut_path), "--force"])
    assert same.exit_code != 0 and "never overwritten" in same.output
    with pytest.raises(ExportError, match="unknown export format"):
        export(table, "stl", tmp_path / "x.stl")
