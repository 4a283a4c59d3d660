"""The whole working volume from one cube placement (issue 26): the cockpit scene, extension sweeps, joint solve.

Cockpit scene (``ivc/sim/scenes/cockpit.toml``), seed 0: the five protocol steps, four extension
sweeps of 20,000 frames and 10,000 check poses uniform over the 0.8 x 0.6 x 0.5 m head box. The
joint solve (``ivc.lut.joint``) maps the box; the baseline in the same run is the single-sweep map
of the same session (``ivc fit`` without the extension sweeps: the harmonic fit around the cube).

Targets: >= 95 % of the box mapped, >= 95 % of the check poses trusted; corrected position median
<= 0.2 mm, p95 <= 1 mm, max <= 5 mm, orientation median <= 1 mrad, in the declared cube frame
(uncorrected beside); where the single-frame noise floor (Cramér-Rao bound at the check poses,
``ivc.sim.noise_floor``) exceeds a target, that target becomes twice the floor (the issue's rule,
applied to the same statistic of the floor; a floor below the target gives no relief). The max is also
given among the poses trusted with a predicted-precision limit (``ivc correct --max-precision``, a
quarter of the max target: a test without truth, from the table's field and the signal noise the fit
measured), with the share of poses that limit leaves trusted; the error
against distance from the cube in fifths, outermost within 2x the innermost at the median; the
whole cockpit pipeline (collect, fit with the joint solve, evaluate) <= 5 minutes and <= 4 GB.
Then the default scene: the equivalent-source fit beside the harmonic fit (the default) on the
single-sweep data, and the default fit's figures against the values bench_lut holds them to.
"""

from __future__ import annotations

import resource
import time

import numpy as np

from benchmarks.harness import Figure
from ivc.correct import Corrector
from ivc.correct.evaluate import check_errors, summarise
from ivc.lut import FitOptions, fit_lut
from ivc.lut.coverage import box_coverage, box_points
from ivc.lut.joint import mapped_litres
from ivc.lut.support import MIN_SUPPORT, node_support
from ivc.session import extension_steps
from ivc.sim import Simulator, load_scene, rig
from ivc.sim.noise_floor import finite_difference_jacobian, pose_noise_floor
from ivc.sim.tracker import noise_sigma
from ivc.table.grid import Grid, GridField

TARGETS_MM = {"p50": 0.2, "p95": 1.0, "max": 5.0}
TARGET_MRAD = 1.0
#: the predicted-precision trust limit of the second max row: a quarter of the max target
PRECISION_LIMIT_MM = TARGETS_MM["max"] / 4


def relieved(target: float, floor: float) -> float:
    """The target a figure is held to: ``target``, or twice the noise floor where the floor exceeds it."""
    return 2.0 * floor if floor > target else target
#: bench_lut's held values of the default fit (refinement on), to show the default is unchanged
DEFAULT_BEFORE = {"p50": 0.04276, "p95": 0.2509}


def _box_fraction(table, volume) -> float:
    """Fraction of the box's volume inside mapped cells (by a 1 cm lattice of points)."""
    return box_coverage(table.field(), volume.center, volume.size)["fraction"]


def _protocol_reach(scene, simulator) -> float:
    """The box share a map would cover if every sensor of every frame the joint fit uses (each extension
    sweep decimated to 5,000 frames) were solved and kept, with the cube's ball (0.19 m): what the sweeps'
    paths allow, whatever the solve does. Only the motion is simulated (no field)."""
    sweeps = []
    for n in range(1, scene.extension.sweeps + 1):
        motion = rig.extension_motion(scene, scene.extension.frames, simulator._rng(f"extension_sweep_{n}"), n)
        positions = simulator.wand.sensor_poses(*motion)[0]
        sweeps.append(positions[:: max(1, -(-len(positions) // 5000))].reshape(-1, 3))
    volume = scene.volume
    lattice = box_points(volume.center, volume.size)
    ball = lattice[np.linalg.norm(lattice - scene.cube.center, axis=1) < 0.19]
    points = np.concatenate([*sweeps, ball])
    grid = Grid.around(points)
    field = GridField(grid, np.zeros((*grid.shape, 3, 3)), node_support(grid, points) >= MIN_SUPPORT)
    return box_coverage(field, volume.center, volume.size)["fraction"]


def _fifths(errors, distance, ok):
    edges = np.linspace(0, distance[ok].max() * (1 + 1e-9), 6)
    medians = []
    for low, high in zip(edges[:-1], edges[1:], strict=True):
        inside = ok & (distance >= low) & (distance < high)
        medians.append(float(np.median(errors[inside])) if inside.any() else float("nan"))
    return edges, medians


def run() -> list[Figure]:
    figures = []
    start = time.perf_counter()
    scene = load_scene("cockpit")
    simulator = Simulator(scene, seed=0)
    session = simulator.protocol()
    collected = time.perf_counter()
    table = fit_lut(session)
    fitted = time.perf_counter()
    errors = check_errors(Corrector(table, session.hemisphere, precision=True), session)  # as `ivc evaluate` does
    report = summarise(errors)
    total = time.perf_counter() - start
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"# cockpit: collect {collected - start:.0f} s, fit {fitted - collected:.0f} s, evaluate "
          f"{time.perf_counter() - fitted:.0f} s (2 shared cores: timings noisy)")
    for step in table.fit["rounds"]:
        print(f"#   round {step['iteration']}: {step['mapped_litres']:.1f} litres mapped, map change "
              f"{step['map_change_mm']} mm, frames solved {step['frames_solved']}")
    for row in table.fit["error_by_distance"]:
        print(f"#   estimated sample error {row['from_mm']:.0f}-{row['to_mm']:.0f} mm from the cube: "
              f"{row['error_p50_mm']:.3f} mm median")

    single = session.select_frames("wand_sweep", slice(None))
    for name in extension_steps(list(single.steps)):
        del single.steps[name], single.truth[name]
    single_start = time.perf_counter()
    single_table = fit_lut(single)
    single_fit = time.perf_counter() - single_start
    single_errors = check_errors(single_table, session)

    volume = scene.volume
    box_joint, box_single = _box_fraction(table, volume), _box_fraction(single_table, volume)
    figures.append(Figure("cockpit: box mapped", 100 * box_joint, "%", "single sweep", 100 * box_single,
                          ">= 95 %", 100 * box_joint >= 95))
    lissajous = load_scene("cockpit")
    lissajous.extension.pattern, lissajous.extension.speed = "lissajous", 0.15  # the sweeps of the rounds before
    figures.append(Figure("cockpit: protocol reach (box share if every used frame were kept)",
                          100 * _protocol_reach(scene, simulator), "%", "Lissajous sweeps at 0.15 m/s",
                          100 * _protocol_reach(lissajous, Simulator(lissajous, seed=0)), "(reference)"))
    valid = errors.valid
    trusted, trusted_single = errors.ok.sum() / valid.sum(), single_errors.ok.sum() / valid.sum()
    figures.append(Figure("cockpit: check poses trusted", 100 * trusted, "%", "single sweep",
                          100 * trusted_single, ">= 95 %", 100 * trusted >= 95))

    truth = session.truth["check"]
    sigma = noise_sigma(scene.noise)
    floor_mm, floor_mrad = pose_noise_floor(truth.position[:, 0], truth.quaternion[:, 0], sigma,
                                            finite_difference_jacobian(simulator.secondary))
    floor_mm, floor_mrad = 1000 * floor_mm, 1000 * floor_mrad
    ok = errors.ok[:, 0]
    position, orientation = errors.ivc_position_mm[:, 0], errors.ivc_orientation_mrad[:, 0]
    dipole_position = report["dipole"]["position_mm"]
    for key, label in (("p50", "median"), ("p95", "p95"), ("max", "max")):
        value = float(np.median(position[ok]) if key == "p50" else
                      np.percentile(position[ok], 95) if key == "p95" else np.max(position[ok]))
        floor = float(np.median(floor_mm[ok]) if key == "p50" else
                      np.percentile(floor_mm[ok], 95) if key == "p95" else np.max(floor_mm[ok]))
        target = relieved(TARGETS_MM[key], floor)
        bound = f"<= {target:.3g} mm" + (" (2x floor)" if target > TARGETS_MM[key] else "")
        figures.append(Figure(f"cockpit: corrected position {label}", value, "mm", "uncorrected",
                              dipole_position[key], bound, value <= target, higher_is_better=False))
        figures.append(Figure(f"cockpit: noise floor (CRB) {label}", floor, "mm", target="(reference)"))
    # the same check, trusting only poses whose predicted precision (from the table's field and the signal noise
    # the fit measured: no truth) is within a quarter of the max target, so that a pose's error 4x its predicted
    # RMS, rare even along one axis (6e-5), would be needed to break the target. The LOW_PRECISION flag of
    # --max-precision is exactly `precision > limit` (tests/test_precision.py), so it is applied to this run's
    # predictions rather than by correcting the check poses a second time
    predicted = errors.precision_mm[:, 0]
    trusted_precise = ok & (predicted <= PRECISION_LIMIT_MM)
    figures.append(Figure(f"cockpit: check poses trusted, --max-precision {PRECISION_LIMIT_MM:g} mm",
                          100 * trusted_precise.sum() / valid[:, 0].sum(), "%", "without the limit", 100 * trusted,
                          ">= 95 %", trusted_precise.sum() / valid[:, 0].sum() >= 0.95))
    value = float(np.max(position[trusted_precise]))
    figures.append(Figure(f"cockpit: corrected position max, --max-precision {PRECISION_LIMIT_MM:g} mm", value, "mm",
                          "without the limit", float(np.max(position[ok])), f"<= {TARGETS_MM['max']:g} mm",
                          value <= TARGETS_MM["max"], higher_is_better=False))
    usable = ok & np.isfinite(predicted)
    figures.append(Figure("cockpit: predicted precision / CRB at the true pose, median", float(
        np.median(predicted[usable] / floor_mm[usable])), "x", target="(reference)"))
    value = float(np.median(orientation[ok]))
    floor = float(np.median(floor_mrad[ok]))
    target = relieved(TARGET_MRAD, floor)
    figures.append(Figure("cockpit: corrected orientation median", value, "mrad", "uncorrected",
                          report["dipole"]["orientation_mrad"]["p50"], f"<= {target:.3g} mrad", value <= target,
                          higher_is_better=False))
    figures.append(Figure("cockpit: noise floor (CRB) orientation median", floor, "mrad", target="(reference)"))

    centre = np.asarray(table.fit["cube_centre"])
    distance = np.linalg.norm(errors.true_position[:, 0] - centre, axis=1)
    edges, medians = _fifths(position, distance, ok)
    for k, median in enumerate(medians):
        inside = ok & (distance >= edges[k]) & (distance < edges[k + 1])
        figures.append(Figure(f"cockpit: median error {1000 * edges[k]:.0f}-{1000 * edges[k + 1]:.0f} mm out",
                              median, "mm", "floor there", float(np.median(floor_mm[inside])) if inside.any()
                              else float("nan"), "(reference)", higher_is_better=False))
    ratio = medians[-1] / medians[0]
    figures.append(Figure("cockpit: outer / inner fifth, median error", ratio, "x", target="<= 2",
                          passed=bool(ratio <= 2), higher_is_better=False))
    figures.append(Figure("cockpit: whole pipeline time", total, "s", "collect + single-sweep fit + evaluate",
                          total - (fitted - collected) + single_fit, "<= 300 s", total <= 300,
                          higher_is_better=False))
    figures.append(Figure("cockpit: joint fit time", fitted - collected, "s", "single-sweep fit", single_fit,
                          "(reference)", higher_is_better=False))
    figures.append(Figure("cockpit: peak memory (RSS)", peak_gb, "GB", target="<= 4 GB", passed=peak_gb <= 4,
                          higher_is_better=False))
    figures.append(Figure("cockpit: mapped volume", mapped_litres(table.grid, table.valid), "litres",
                          "single sweep", mapped_litres(single_table.grid, single_table.valid), "(reference)"))

    default = Simulator(load_scene("default"), seed=0).protocol()
    harmonic = summarise(check_errors(fit_lut(default, FitOptions()), default))
    sources = summarise(check_errors(fit_lut(default, FitOptions(fitter="sources")), default))
    for key, label in (("p50", "median"), ("p95", "p95")):
        h, s = harmonic["ivc"]["position_mm"][key], sources["ivc"]["position_mm"][key]
        figures.append(Figure(f"default: harmonic (default fit) {label}", h, "mm", "bench_lut's held value",
                              DEFAULT_BEFORE[key], f"<= {1.02 * DEFAULT_BEFORE[key]:.4g} mm",
                              h <= 1.02 * DEFAULT_BEFORE[key], higher_is_better=False))
        figures.append(Figure(f"default: equivalent sources {label}", s, "mm", "harmonic", h, "(reference)",
                              higher_is_better=False))
    return figures
