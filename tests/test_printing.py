"""Printable fixtures (issue 40): every sensor model's cube and wand, at the parameters' limits, is watertight,
prints without overhangs, and has its pockets where its geometry file says; what does not fit is refused."""

import re
import zipfile
from xml.etree import ElementTree

import numpy as np
import pytest

from ivc.errors import FixtureError
from ivc.fixtures.geometry import MIN_WALL, PartOptions, cube_layout, min_pitch, read_geometry, wand_layout, wand_pitch
from ivc.fixtures.sensors import MM, SENSORS, custom_sensor

pytest.importorskip("manifold3d")

from ivc.fixtures.printing import build_part, glyph_strokes, print_fixture, write_part  # noqa: E402

MODELS = [*SENSORS, "custom:20x6", "custom:12x8x5"]


def _smallest(make, what: str):
    """The layout at the smallest size the refusal message proposes (it must fit)."""
    try:
        make(1 * MM)
    except FixtureError as error:
        need = float(re.search(rf"use {what} >= ([0-9.]+) mm", str(error)).group(1))
        return make(need * MM)
    raise AssertionError("a 1 mm layout was not refused")


def _hits(mesh, origin, direction):
    """Distances (sorted) at which the ray from ``origin`` along unit ``direction`` crosses the mesh's triangles
    (Möller and Trumbore 1997, every triangle at once)."""
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    d = np.asarray(direction, float)
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
    s = np.asarray(origin, float) - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-12)
    return np.sort(t[hit])


def _ray(mesh, origin, direction):
    """Distance to the first hit along ``direction`` from ``origin`` (inf: none)."""
    hits = _hits(mesh, origin, direction)
    return float(hits[0]) if len(hits) else np.inf


def _inside(mesh, point) -> bool:
    """A point is inside a closed mesh when a ray from it crosses the surface an odd number of times."""
    return len(_hits(mesh, point, np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81]))) % 2 == 1


def check_part(geometry):
    part = build_part(geometry)
    mesh, printable = part.assembled, part.printable
    assert mesh.is_watertight and mesh.volume > 0 and printable.is_watertight
    assert printable.volume == pytest.approx(mesh.volume, rel=1e-6)
    # print orientation: every face that looks down more steeply than 45 degrees lies on the bed (slivers of
    # under 0.001 mm² left in a flat face by the booleans have no direction to speak of)
    down = (printable.face_normals[:, 2] < -np.cos(np.radians(45))) & (printable.area_faces > 1e-9)
    assert np.allclose(printable.vertices[printable.faces[down]][..., 2], printable.bounds[0, 2], atol=1e-9)
    sensor, c = geometry.sensor, geometry.options.clearance
    centres, R_b = geometry.body_poses()
    tops = np.array([plate[1][2] for plate in _plates(geometry)])
    for n, p in enumerate(geometry.positions):
        assert not _inside(mesh, p), f"sensor {n}'s origin is inside the solid"
        floor = p[2] - (centres[n, 2] - sensor.height / 2) + c  # the pocket's floor under the origin
        assert _inside(mesh, p - [0, 0, floor + geometry.options.floor / 2])  # the floor under it is solid
        below = _ray(mesh, p, [0, 0, -1])
        assert below == pytest.approx(floor, abs=0.01 * MM), f"sensor {n}: floor {below} for {floor}"
        assert p[2] + _ray(mesh, p, [0, 0, 1]) > tops.min() - 1e-9  # the pocket opens upwards
        across = R_b[n][:, 1]  # body y: the side walls, half the body's width (ears included) and clearance away
        offset = (p - centres[n]) @ across
        for sign in (1, -1):
            wall = sensor.footprint[1] / 2 + c - sign * offset
            assert _ray(mesh, p, sign * across) == pytest.approx(wall, abs=0.01 * MM), f"sensor {n}"
    return part


def _plates(geometry):
    from ivc.fixtures.geometry import layout

    return layout(geometry).plates


@pytest.mark.parametrize("model", MODELS)
def test_every_sensor_models_cube_is_printable_and_its_pockets_sit_at_the_file_poses(model):
    part = check_part(cube_layout(model))
    assert len(part.printable.split(only_watertight=True)) == 2  # two plates, joined by nylon screws


@pytest.mark.parametrize("model", MODELS)
def test_every_sensor_models_wand_is_printable_and_its_pockets_sit_at_the_file_poses(model):
    check_part(wand_layout(model, 8, wand_pitch(model)))


@pytest.mark.parametrize("model", ["liberty-rx2", "aurora-6dof", "ndi-8mm"])
def test_parts_at_the_limits_of_their_parameters(model):
    thin = PartOptions(clearance=0.0, wall=MIN_WALL, floor=MIN_WALL)
    check_part(_smallest(lambda e: cube_layout(model, e, thin), "edge"))
    check_part(_smallest(lambda p: wand_layout(model, 2, p), "pitch"))
    check_part(wand_layout(model, 2, min_pitch(model)))
    check_part(cube_layout(model, 0.15, PartOptions(clearance=2 * MM)))
    check_part(wand_layout(model, 16, 0.05))


def test_what_does_not_fit_is_refused_with_the_numbers():
    with pytest.raises(FixtureError, match=r"pockets of sensors \d and \d leave a wall of -3\.30 mm .* pitch 25\.40 "
                                           r"mm .* use pitch >= 30\.2 mm"):
        wand_layout("liberty-rx2", 8, 0.0254)
    with pytest.raises(FixtureError, match="wall 1.40 mm is under the 1.5 mm"):
        cube_layout("liberty-rx2", options=PartOptions(wall=1.4 * MM))
    with pytest.raises(FixtureError, match="use edge >= "):
        cube_layout("liberty-rx2", 0.03)
    with pytest.raises(FixtureError, match="unknown sensor model 'rx9'"):
        cube_layout("rx9")
    assert wand_pitch("liberty-rx2") == pytest.approx(30.2 * MM)
    assert wand_pitch("aurora-6dof") == pytest.approx(25.4 * MM)


def test_engraved_glyphs_are_strokes_inside_their_box():
    strokes = np.array(glyph_strokes("10"))
    assert len(strokes) == len("bc") + len("abcdef")
    # centred on the two 1-wide glyphs 0.6 apart (2.6 wide); the 1 is its right-hand strokes only
    assert np.all(np.abs(strokes[..., 1]) <= 1) and strokes[..., 0].min() == pytest.approx(-0.3)
    assert strokes[..., 0].max() == pytest.approx(1.3)
    with pytest.raises(FixtureError):
        glyph_strokes("?")


def test_print_fixture_writes_the_part_its_geometry_and_preview(tmp_path):
    part, paths = print_fixture("cube", tmp_path / "cube.3mf", sensor=custom_sensor(0.02, 0.008))
    assert [p.exists() for p in paths] == [True, True, True]
    with zipfile.ZipFile(paths[0]) as package:
        model = ElementTree.fromstring(package.read("3D/3dmodel.model"))
    ns = {"m": "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"}
    assert model.get("unit") == "millimeter"
    assert len(model.findall(".//m:triangle", ns)) == len(part.printable.faces)
    geometry = read_geometry(paths[1])
    assert np.allclose(geometry.positions, part.geometry.positions)
    assert paths[2].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(FixtureError, match="exist"):
        print_fixture("cube", tmp_path / "cube.3mf")
    with pytest.raises(FixtureError, match=r"\.stl or \.3mf"):
        write_part(part, tmp_path / "cube.obj")


def test_the_fixtures_command_keeps_its_session_form_beside_print(tmp_path):
    import json

    from click.testing import CliRunner

    from ivc import session as session_io
    from ivc.cli import cli
    from ivc.sim import Simulator
    from ivc.sim.scene import scene_from_dict

    runner = CliRunner()
    printed = runner.invoke(cli, ["fixtures", "print", "cube", "-o", str(tmp_path / "cube.stl"), "--sensor",
                                  "ndi-8mm"])
    assert printed.exit_code == 0, printed.output
    wand = runner.invoke(cli, ["fixtures", "print", "wand", "-o", str(tmp_path / "wand.stl"), "--pitch", "1in",
                               "--sensor", "aurora-6dof"])
    assert wand.exit_code == 0, wand.output
    assert read_geometry(tmp_path / "wand.json").parameters["pitch"] == pytest.approx(0.0254)
    refused = runner.invoke(cli, ["fixtures", "print", "wand", "-o", str(tmp_path / "w.stl"), "--pitch", "20mm"])
    assert refused.exit_code != 0 and "use pitch >= 30.2 mm" in refused.output
    assert not (tmp_path / "w.stl").exists()

    scene = scene_from_dict({"conductor": [{"shape": "plate", "size": [1.0, 1.0], "position": [0.5, 0, -0.35],
                                            "material": "aluminium", "resolution_mm": 80}]})
    scene.tabulate = False
    simulator = Simulator(scene, seed=3, cube_geometry=read_geometry(tmp_path / "cube.json"))
    session = simulator.protocol({"cube_calibration": 200, "cube_survey": 100, "wand_calibration": 100,
                                  "wand_sweep": 300, "check": 10})
    path = tmp_path / "s.h5"
    session_io.write(session, path)
    for form in (["fixtures", str(path)], ["fixtures", "report", str(path)]):
        result = runner.invoke(cli, [*form, "--geometry", str(tmp_path / "cube.json")])
        assert result.exit_code == 0, result.output
        assert "fitted perfect cube edge" in result.output
        assert "Cube matches its geometry file" in result.output
    report = json.loads(runner.invoke(cli, ["fixtures", str(path), "--json", "--geometry",
                                            str(tmp_path / "cube.json"), "--geometry",
                                            str(tmp_path / "wand.json")]).output)
    checks = {check["kind"]: check for check in report["build_checks"]}
    assert checks["cube"]["ok"]
    # the scene's hand-built wand is not the printed one the file describes
    assert not checks["wand"]["ok"] and checks["wand"]["findings"][0]["kind"] == "wrong fixture"


def test_without_manifold3d_the_error_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "manifold3d", None)  # an import of it now raises ImportError
    with pytest.raises(FixtureError, match=r"pip install 'ivc\[print\]'"):
        build_part(cube_layout())
