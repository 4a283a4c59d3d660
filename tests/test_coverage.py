"""Coverage of a declared working volume: the session's attributes, the table's share of the box, and the
simulated extension sweeps' passes that reach all of it (issue 26)."""

import numpy as np
import pytest

from ivc import session as session_io
from ivc.errors import InputError
from ivc.lut.coverage import box_coverage, box_points
from ivc.lut.support import node_support
from ivc.report import box_section
from ivc.session import SessionError, working_volume
from ivc.sim import Simulator, load_scene, rig
from ivc.sim.scene import SceneError, scene_from_dict
from ivc.table.grid import Grid, GridField

CENTER, SIZE = np.array([0.55, 0.0, 0.0]), np.array([0.8, 0.6, 0.5])


def _field(valid_from_x: float | None = None) -> GridField:
    grid = Grid(CENTER - SIZE / 2 - 0.05, 0.05, (19, 15, 13))
    valid = np.ones(grid.shape, dtype=bool)
    if valid_from_x is not None:
        valid &= grid.nodes()[..., 0] >= valid_from_x
    return GridField(grid, np.zeros((*grid.shape, 3, 3)), valid)


def test_box_points_fill_the_box_evenly():
    points = box_points(CENTER, SIZE, 0.01)
    assert points.shape == (80 * 60 * 50, 3)
    np.testing.assert_allclose(points.mean(axis=0), CENTER, atol=1e-12)
    assert np.all(points > CENTER - SIZE / 2) and np.all(points < CENTER + SIZE / 2)
    with pytest.raises(InputError):
        box_points(CENTER, [0.8, 0.0, 0.5])
    with pytest.raises(InputError):
        box_points(CENTER, SIZE, step=-1)


def test_box_coverage_is_the_mapped_share_of_the_box():
    full = box_coverage(_field(), CENTER, SIZE)
    assert full["fraction"] == 1.0 and full["mapped_litres"] == pytest.approx(240.0)
    assert set(full["faces"]) == {"-x", "+x", "-y", "+y", "-z", "+z"}
    # nodes valid from x = 0.55 + 0.05 k: cells fully mapped from the first valid node plane on
    half = box_coverage(_field(valid_from_x=0.55), CENTER, SIZE)
    assert half["fraction"] == pytest.approx(0.5, abs=0.01)
    assert half["faces"]["-x"] == 0.0 and half["faces"]["+x"] == 1.0
    assert "50.0 %" in box_section(half) and "240 litres" in box_section(half)
    assert "declares no working volume" in box_section(None)


def test_the_working_volume_is_declared_by_two_attributes(tmp_path):
    assert working_volume({}) is None
    center, size = working_volume({"working_volume_center": [0.5, 0, 0], "working_volume_size": [0.8, 0.6, 0.5]})
    np.testing.assert_array_equal(size, [0.8, 0.6, 0.5])
    with pytest.raises(SessionError, match="without working_volume_size"):
        working_volume({"working_volume_center": [0.5, 0, 0]})
    with pytest.raises(SessionError, match="positive sizes"):
        working_volume({"working_volume_center": [0.5, 0, 0], "working_volume_size": [0.8, -0.6, 0.5]})
    with pytest.raises(SessionError, match="three finite"):
        working_volume({"working_volume_center": [0.5, 0], "working_volume_size": [0.8, 0.6, 0.5]})
    # the simulator declares its scene's volume, and the file keeps it
    scene = scene_from_dict({"volume": {"center": [0.55, 0, 0], "size": [0.8, 0.6, 0.5]},
                             "cube": {"center": [0.55, 0, 0]}})  # free space: nothing to solve
    session = Simulator(scene, seed=0).protocol({"check": 20}, steps=["check"])
    path = tmp_path / "s.h5"
    session_io.write(session, path)
    center, size = working_volume(session_io.read(path).attrs)
    np.testing.assert_array_equal(center, scene.volume.center)
    np.testing.assert_array_equal(size, scene.volume.size)
    assert working_volume(Simulator(scene_from_dict({})).protocol({"check": 5}, steps=["check"]).attrs) is None


def _sweep_positions(scene, seed=0):
    sim = Simulator(scene, seed=seed)
    return np.array([sim.wand.sensor_poses(*rig.extension_motion(scene, scene.extension.frames,
                                                                  sim._rng(f"extension_sweep_{n}"), n))[0]
                     for n in range(1, scene.extension.sweeps + 1)])


def test_the_passes_reach_every_corner_of_the_cockpit_box_continuously():
    scene = load_scene("cockpit")
    positions = _sweep_positions(scene)  # (sweeps, F, W, 3)
    volume = scene.volume
    reach = -rig.PASS_MARGIN + 0.005  # the outermost passes run just beyond the faces (the wand bent by mm)
    assert np.all(positions >= volume.lower - reach) and np.all(positions <= volume.upper + reach)
    assert positions[..., 0].max() > volume.upper[0] and positions[..., 0].min() < volume.lower[0]
    hand = positions[:, :, -1]
    step = np.linalg.norm(np.diff(hand, axis=1), axis=-1) * scene.sweep_rate_hz  # m/s, within a sweep
    assert np.median(step) == pytest.approx(scene.extension.speed, rel=0.1)
    assert step.max() < 3 * scene.extension.speed  # no jumps: a walk a person can make
    corners = volume.center + volume.size / 2 * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1)
                                                          for z in (-1, 1)])
    nearest = np.linalg.norm(hand.reshape(-1, 1, 3) - corners[None], axis=-1).min(axis=0)
    assert nearest.max() < 0.03, f"the hand comes within {1000 * nearest.max():.0f} mm of the farthest corner"
    # the tip points back at the cube: sensor 0 nearer the cube than the hand in (nearly) every frame
    distance = np.linalg.norm(positions - scene.cube.center, axis=-1)
    assert np.mean(distance[..., 0] < distance[..., -1]) > 0.95
    # every sensor position kept (as if every frame were solved) maps the whole box, the cube's ball aside
    points = np.concatenate([positions[:, ::4].reshape(-1, 3)])
    grid = Grid.around(points, 0.0381)
    field = GridField(grid, np.zeros((*grid.shape, 3, 3)), node_support(grid, points) >= 20)
    assert box_coverage(field, volume.center, volume.size)["fraction"] > 0.98


def test_the_lissajous_pattern_is_kept_and_unknown_patterns_are_refused():
    data = {"volume": {"center": [0.55, 0, 0], "size": [0.6, 0.5, 0.4]}, "cube": {"center": [0.55, 0, 0]},
            "extension": {"sweeps": 2, "frames": 2000, "pattern": "lissajous"}}
    scene = scene_from_dict(data)
    positions = _sweep_positions(scene)
    assert np.all(positions >= scene.volume.lower) and np.all(positions <= scene.volume.upper)
    assert not np.allclose(positions[0], positions[1])
    with pytest.raises(SceneError, match="pattern"):
        scene_from_dict({**data, "extension": {"sweeps": 1, "pattern": "zigzag"}})
