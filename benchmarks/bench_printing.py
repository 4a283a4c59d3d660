"""Printable fixtures and the build check (issue 40).

Generation: laying out and meshing the default cube (Liberty RX2, 50.8 mm) and wand (8 Aurora 6DOF at
25.4 mm, and 8 RX2 at their smallest pitch), target < 2 s each; baseline, same run: one bare trimesh box
minus a box through manifold3d (the cost of the boolean machinery itself).

Build check: 100 random builds of the cube and 100 of the wand (``ivc.sim.rig.random_build``: half correct
prints, half with a swapped pair, a sensor turned 2-90 deg and/or a sensor moved 1-4 mm), each calibrated in
free space with the default scene's noise. Target: every swapped pair named, every sensor more than 1 mm or
2 deg from its nominal pose flagged, nothing flagged on a correct build, and no sensor within 0.5 mm and 1 deg
of nominal flagged in any build (a fault lies between 1 and 4 mm or 2 and 90 deg; with the print's errors a
faulty sensor may land between the tolerances and 1 mm / 2 deg, where either answer is right). Baseline, same
run: a plain
least-squares alignment of all sensors (no consensus) with the same tolerances.
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.harness import Figure, best_time
from ivc import rotations
from ivc.fixtures.build_check import Tolerances, check_cube, check_wand
from ivc.fixtures.cube import CubeCalibration
from ivc.fixtures.geometry import cube_layout, wand_layout, wand_pitch
from ivc.fixtures.printing import build_part
from ivc.fixtures.wand import WandCalibration
from ivc.sim import Simulator, load_scene, rig

BUILDS = 100
FRAMES = 200  # frames averaged per static calibration


def _box_boolean():
    import trimesh

    a = trimesh.creation.box((80.0, 80.0, 20.0))
    b = trimesh.creation.box((20.0, 20.0, 20.0))
    b.apply_translation((0.0, 0.0, 10.0))
    return trimesh.boolean.difference([a, b], engine="manifold")


def _plain_flags(positions, quaternions, geometry, tolerances: Tolerances) -> np.ndarray:
    """The baseline: Kabsch over every sensor as paired by index, then the same thresholds."""
    P, Q = positions, geometry.positions
    H = (Q - Q.mean(0)).T @ (P - P.mean(0))
    U, _, Vt = np.linalg.svd(H)
    A = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    aligned = (P - P.mean(0)) @ A.T + Q.mean(0)
    angle = rotations.angle_between_matrices(A @ rotations.to_matrix(quaternions), geometry.matrices)
    return (np.linalg.norm(aligned - Q, axis=1) > tolerances.position) | (angle > tolerances.angle)


def _builds(kind: str, geometry, seed: int) -> dict:
    simulator = Simulator(load_scene("default"), seed=seed, cube_geometry=geometry if kind == "cube" else None,
                          wand_geometry=geometry if kind == "wand" else None)
    rng = np.random.default_rng(seed)
    origin = None if kind == "cube" else geometry.positions[0]
    tally = {"must": 0, "caught": 0, "pairs": 0, "named": 0, "correct": 0, "false": 0, "plain_caught": 0,
             "plain_false": 0, "clean": 0, "innocent": 0, "plain_innocent": 0, "seconds": 0.0}
    for _ in range(BUILDS):
        fixture, faults = rig.random_build(geometry, rng, origin=origin)
        setattr(simulator, kind, fixture)
        step = simulator.step(f"{kind}_calibration", FRAMES)[0]
        start = time.perf_counter()
        if kind == "cube":
            calibration = CubeCalibration.from_step(step)
            report = check_cube(calibration, geometry)
            poses = calibration.relative_positions, calibration.relative_quaternions
        else:
            calibration = WandCalibration.from_step(step)
            report = check_wand(calibration, geometry)
            poses = calibration.positions, rotations.from_matrix(calibration.rotations)
        tally["seconds"] += time.perf_counter() - start
        position, angle = rig.build_deviations(geometry, fixture, origin)
        must = (position > 1e-3) | (angle > np.radians(2))
        clean = (position < 0.5e-3) & (angle < np.radians(1))  # a correct print's sensor
        flagged = np.zeros(geometry.n_sensors, bool)
        for finding in report.findings:
            flagged[list(finding.sensors)] = True
        plain = _plain_flags(*poses, geometry, Tolerances())
        tally["must"] += int(must.sum())
        tally["caught"] += int((flagged & must).sum())
        tally["plain_caught"] += int((plain & must).sum())
        named = {f.sensors for f in report.findings if f.kind == "swapped"}
        tally["pairs"] += len(faults["swaps"])
        tally["named"] += sum(tuple(sorted(p)) in named for p in faults["swaps"])
        tally["clean"] += int(clean.sum())
        tally["innocent"] += int((flagged & clean).sum())
        tally["plain_innocent"] += int((plain & clean).sum())
        if not (faults["swaps"] or faults["turns"] or faults["lifts"]):
            tally["correct"] += 1
            tally["false"] += int(flagged.any())
            tally["plain_false"] += int(plain.any())
    return tally


def run() -> list[Figure]:
    figures = []
    baseline = best_time(_box_boolean, repeat=3)
    parts = {"cube, liberty-rx2, 50.8 mm": lambda: build_part(cube_layout("liberty-rx2", 0.0508)),
             "wand, 8 aurora-6dof, 25.4 mm": lambda: build_part(wand_layout("aurora-6dof", 8, 0.0254)),
             "wand, 8 liberty-rx2, 30.2 mm": lambda: build_part(wand_layout("liberty-rx2", 8,
                                                                            wand_pitch("liberty-rx2")))}
    for name, make in parts.items():
        seconds = best_time(make, repeat=3)
        figures.append(Figure(f"generate {name}", seconds, "s", "trimesh box - box", baseline, "< 2 s",
                              seconds < 2.0, higher_is_better=False))
    for kind, geometry, seed in (("cube", cube_layout("liberty-rx2"), 40), ("wand", wand_layout("aurora-6dof"), 41)):
        t = _builds(kind, geometry, seed)
        figures.append(Figure(f"{kind}: faulty sensors flagged (of {t['must']})", t["caught"], "sensors",
                              "plain alignment", t["plain_caught"], f"all {t['must']}", t["caught"] == t["must"]))
        figures.append(Figure(f"{kind}: swapped pairs named (of {t['pairs']})", t["named"], "pairs", "", np.nan,
                              f"all {t['pairs']}", t["named"] == t["pairs"]))
        figures.append(Figure(f"{kind}: false alarms ({t['correct']} correct builds)", t["false"], "builds",
                              "plain alignment", t["plain_false"], "0", t["false"] == 0, higher_is_better=False))
        figures.append(Figure(f"{kind}: sound sensors flagged (of {t['clean']})", t["innocent"], "sensors",
                              "plain alignment", t["plain_innocent"], "0", t["innocent"] == 0, higher_is_better=False))
        figures.append(Figure(f"{kind}: check time per build", 1000 * t["seconds"] / BUILDS, "ms", "", np.nan, "-",
                              None, higher_is_better=False))
    return figures
