"""Pose-only trackers (issue 21): map and correct from reported poses alone, default scene.

The default protocol (seed 0: 100,000-frame sweep, 10,000 check poses) is simulated once and
its signals are removed from every step; ``ivc fit`` then maps from the reported poses alone and
the check poses are corrected through the pose path. Targets, errors in the declared cube frame:
median <= 0.08 mm and <= 0.3 mrad, 95th <= 0.5 mm, >= 95 % trusted. Beside it, the same protocol
reported by a ``least-squares`` tracker while ivc assumes ``closed-form`` (what the mismatch
costs), and a stream (``PoseCorrector.update``, the call the live loop makes per round: the wand
sweep's first frames, a moving fixture's sensors) against the batch of the same samples: >= 95 %
trusted, the same accuracy. Speed: >= 100,000 sensor-frames/s batched, <= 100 µs median per 4-sensor
streamed frame (the 8-sensor wand frame beside). Exports: the ``slicer-itk`` field applied with
SimpleITK to the reported check positions (those ivc trusts) lands within 0.1 mm of ``ivc correct``
(median), 1 mm (99th percentile) and none over 10 mm where the file's field is defined; the Vrui
grid's coverage of the same positions beside the table's own grid's.

Baselines in the same run: the tracker's own (uncorrected) reported poses, the NumPy reference
inversion (:func:`ivc.pose.reported.invert_distortion`) and the signal path's streaming step on
the same frames. The machine is shared: timings are noisy.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.harness import Figure, best_time
from ivc import dipole, rotations
from ivc.cli.evaluate import render_table
from ivc.correct import Corrector
from ivc.correct.evaluate import check_errors, summarise
from ivc.correct.reported import PoseCorrector
from ivc.export import distortion, export
from ivc.export.formats import LPS, SUBDIVISION
from ivc.fixtures.reported_mapping import PoseFixtureModel, map_sweep_poses
from ivc.lut import FitOptions, fit_lut
from ivc.lut.correction_table import fit_pose_domain_table
from ivc.pose.reported import invert_distortion
from ivc.session import Session
from ivc.sim import Simulator, load_scene
from ivc.truth import declared_frame_map

#: sweep frames streamed through PoseCorrector.update
STREAM_FRAMES = 5000


def _sessions() -> tuple[Session, Session]:
    """The default protocol reported by a closed-form and by a least-squares tracker, signals removed."""
    scene = load_scene("default")
    simulator = Simulator(scene, seed=0)
    mismatch = Simulator(replace(scene, solver="least-squares"), seed=0)
    mismatch.__dict__["secondary"] = simulator.secondary  # the same room: solve its eddy currents once
    out = []
    for sim in (simulator, mismatch):
        session = Session(hemisphere=scene.hemisphere)
        for name in ("cube_calibration", "cube_survey", "wand_calibration", "wand_sweep", "check"):
            step, session.truth[name] = sim.step(name)
            session.steps[name] = replace(step, signal=None)
        out.append(session)
    return out[0], out[1]


def _accuracy_figures(label: str, report: dict, baseline: dict | None, targets: bool) -> list[Figure]:
    ivc = report["ivc"]
    trusted = 100 * report["corrected"] / report["samples"]
    rows = [("position median", ivc["position_mm"]["p50"], "mm", 0.08),
            ("orientation median", ivc["orientation_mrad"]["p50"], "mrad", 0.3),
            ("position 95th", ivc["position_mm"]["p95"], "mm", 0.5)]
    figures = []
    for name, value, unit, target in rows:
        kind = "position_mm" if unit == "mm" else "orientation_mrad"
        key = "p95" if "95th" in name else "p50"
        if baseline is None:
            base_name, base = "reported (uncorrected)", report["dipole"][kind][key]
        else:
            base_name, base = "matched solvers", baseline["ivc"][kind][key]
        figures.append(Figure(f"{label}: {name}", value, unit, base_name, base,
                              f"<= {target:g} {unit}" if targets else "", passed=(value <= target) if targets else None,
                              higher_is_better=False))
    base_trusted = None if baseline is None else 100 * baseline["corrected"] / baseline["samples"]
    figures.append(Figure(f"{label}: trusted", trusted, "%", "" if baseline is None else "matched solvers",
                          float("nan") if base_trusted is None else base_trusted, ">= 95 %" if targets else "",
                          passed=(trusted >= 95) if targets else None))
    return figures


def _pose_domain_figures(session: Session, matched: dict) -> list[Figure]:
    """The alternative: a table of the correction itself over the reported positions (ivc.lut.correction_table),
    fitted to the same wand pairs, on the same check poses."""
    stride = max(1, -(-session.steps["wand_sweep"].n_frames // FitOptions().max_frames))
    thinned = session.select_frames("wand_sweep", slice(None, None, stride))
    model = PoseFixtureModel.from_session(thinned)
    table = fit_pose_domain_table(map_sweep_poses(thinned, model).pairs)
    check, truth = session.steps["check"], session.truth["check"]
    valid = check.valid_mask.reshape(-1)
    Q = rotations.to_matrix(np.where(valid[:, None], check.quaternion.reshape(-1, 4), [1.0, 0.0, 0.0, 0.0]))
    r, T, mapped = table.correct(check.position.reshape(-1, 3), Q)
    ok = mapped & valid
    D_R, D_t, _ = declared_frame_map(session)
    true_r = truth.position.reshape(-1, 3) @ D_R.T + D_t
    true_T = D_R @ rotations.to_matrix(truth.quaternion.reshape(-1, 4))
    position = 1000 * np.linalg.norm(r[ok] - true_r[ok], axis=1)
    angle = 1000 * rotations.angle_between_matrices(T[ok], true_T[ok])
    return [Figure("pose-domain table: position median", float(np.median(position)), "mm", "physical table",
                   matched["ivc"]["position_mm"]["p50"], higher_is_better=False),
            Figure("pose-domain table: orientation median", float(np.median(angle)), "mrad", "physical table",
                   matched["ivc"]["orientation_mrad"]["p50"], higher_is_better=False),
            Figure("pose-domain table: within its table", 100 * float(ok.mean()), "%", "physical table trusted",
                   100 * matched["corrected"] / matched["samples"])]


def _vrui_lookup(c: distortion.DistortionGrid, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vrui's ForwardGridCalibrator applied to reported positions v (n, 3) m (its vertices are the grid's valid
    nodes, tests/test_export.py reads the file as Vrui does): (corrected positions, whether Vrui corrects)."""
    g = c.grid
    u = (v - g.origin) / g.spacing
    index = np.clip(np.floor(u).astype(int), 0, np.array(g.shape) - 2)
    w = u - index
    offset = np.where(c.valid[..., None], c.target - np.einsum("...ij,...j->...i", np.nan_to_num(c.turn), c.source),
                      0.0)
    rotvec = c.rotation_vector
    o, rv = np.zeros_like(v), np.zeros_like(v)
    for corner in np.ndindex(2, 2, 2):
        k = index + np.array(corner)
        weight = np.prod(np.where(np.array(corner, bool), w, 1 - w), axis=1)[:, None]
        o += weight * offset[k[:, 0], k[:, 1], k[:, 2]]
        rv += weight * rotvec[k[:, 0], k[:, 1], k[:, 2]]
    corrected = o + np.einsum("nij,nj->ni", rotations.to_matrix(rotations.from_rotvec(rv)), v)
    return corrected, c.defined_at(v)


def _export_figures(table, session: Session, batch) -> list[Figure]:
    """The reported->true exports over the reported region, applied as their consumers apply them to the
    reported check positions, against ivc correct's corrections of the same poses."""
    import SimpleITK as sitk

    check = session.steps["check"]
    v = check.position.reshape(-1, 3)
    trusted = batch.flags.reshape(-1) == 0
    corrected = batch.position.reshape(-1, 3)
    v, corrected = v[trusted], corrected[trusted]
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        path = export(table, "itk", Path(tmp) / "room_itk.h5")
        seconds = time.perf_counter() - start
        transform = sitk.ReadTransform(str(path))
        moved = np.array([transform.TransformPoint(tuple(p)) for p in (v * LPS * 1000.0).tolist()]) * LPS / 1000.0
    itk_grid = distortion.reported_correction(table, table.grid.spacing / SUBDIVISION["itk"])
    inside = itk_grid.defined_at(v)
    gap = 1000 * np.linalg.norm(moved - corrected, axis=1)
    raw = 1000 * np.linalg.norm(v - corrected, axis=1)
    old = distortion.correction(table)  # the table's own grid (true positions), as the exports had it
    old_covered = old.defined_at(v)
    name = "slicer-itk (SimpleITK) vs ivc correct"
    figures = [
        Figure(f"{name}: median", float(np.median(gap)), "mm", "uncorrected", float(np.median(raw)), "<= 0.1 mm",
               passed=np.median(gap) <= 0.1, higher_is_better=False),
        Figure(f"{name}: 99th", float(np.percentile(gap, 99)), "mm", "uncorrected", float(np.percentile(raw, 99)),
               "<= 1 mm", passed=np.percentile(gap, 99) <= 1.0, higher_is_better=False),
        Figure(f"{name}: over 10 mm, mapped", float(np.sum(gap[inside] > 10)), "poses", "all trusted poses",
               float(np.sum(gap > 10)), "0", passed=not np.any(gap[inside] > 10), higher_is_better=False),
        Figure(f"{name}: max, mapped", float(np.max(gap[inside])), "mm", "all trusted poses", float(np.max(gap)),
               higher_is_better=False),
        Figure("slicer-itk: trusted poses in its mapped volume", 100 * float(inside.mean()), "%",
               "table's grid (true positions)", 100 * float(old_covered.mean())),
        Figure(f"slicer-itk: export ({itk_grid.grid.spacing * 1000:.2f} mm grid)", seconds, "s",
               higher_is_better=False),
    ]
    vrui = distortion.reported_correction(table, table.grid.spacing / SUBDIVISION["vrui"])
    landed, corrects = _vrui_lookup(vrui, v)
    vrui_gap = 1000 * np.linalg.norm(landed[corrects] - corrected[corrects], axis=1)
    figures += [
        Figure("vrui: trusted poses it corrects", 100 * float(corrects.mean()), "%", "table's grid (true positions)",
               100 * float(old_covered.mean())),
        Figure("vrui vs ivc correct: median, where it corrects", float(np.median(vrui_gap)), "mm", "uncorrected",
               float(np.median(raw[corrects])), higher_is_better=False),
        Figure("vrui vs ivc correct: 99th, where it corrects", float(np.percentile(vrui_gap, 99)), "mm",
               "uncorrected", float(np.percentile(raw[corrects], 99)), higher_is_better=False),
    ]
    return figures


def _stream(table, v: np.ndarray, Q: np.ndarray, names: list) -> tuple[list, np.ndarray, np.ndarray]:
    """Frames of reported positions v (F, N, 3) and rotations Q (F, N, 3, 3) through ``PoseCorrector.update`` (the
    live loop's call), after one warm-up frame: each frame's latency (s), and the flags and positions of all."""
    stream = PoseCorrector(table)
    stream.update(v[0], Q[0], sensors=names)
    stream.reset()
    latency, flags, position = [], [], []
    for k in range(len(v)):
        t0 = time.perf_counter()
        out = stream.update(v[k], Q[k], sensors=names)
        latency.append(time.perf_counter() - t0)
        flags.append(out.flags)
        position.append(out.position)
    return latency, np.concatenate(flags), np.concatenate(position)


def run() -> list[Figure]:
    start = time.perf_counter()
    session, mismatch = _sessions()
    simulated = time.perf_counter() - start
    start = time.perf_counter()
    table = fit_lut(session, FitOptions())
    fitted = time.perf_counter() - start
    mismatch_table = fit_lut(mismatch, FitOptions())
    corrector = PoseCorrector(table)
    matched = summarise(check_errors(corrector, session))
    wrong = summarise(check_errors(PoseCorrector(mismatch_table), mismatch))
    print(f"\n--- from reported poses alone (closed-form tracker), fit in {fitted:.0f} s, "
          f"simulated in {simulated:.0f} s ---\n{render_table(matched)}")
    print(f"\n--- least-squares tracker, ivc assuming closed-form ---\n{render_table(wrong)}\n")
    figures = _accuracy_figures("pose-only", matched, None, True)
    figures += _pose_domain_figures(session, matched)
    figures += _accuracy_figures("solver mismatch (sim LS, ivc CF)", wrong, matched, False)

    # the stream: the wand sweep's frames (a moving fixture's sensors, as a live stream sends them) through
    # PoseCorrector.update (the live loop's call), against the batch of the same samples
    sweep = session.steps["wand_sweep"]
    frames = slice(0, STREAM_FRAMES)
    names = list(sweep.sensor_ids)
    v = sweep.position[frames]
    valid = sweep.valid_mask[frames]
    Q = rotations.to_matrix(np.where(valid[..., None], sweep.quaternion[frames], [1.0, 0.0, 0.0, 0.0]))
    Q[~valid] = np.nan
    latency, flags, position = _stream(table, v, Q, names)
    check = session.steps["check"]
    batch = corrector.batch(check.position, check.quaternion, check.valid_mask)
    figures += _export_figures(table, session, batch)
    swept = corrector.batch(sweep.position[frames], sweep.quaternion[frames], valid)
    ok = (flags == 0) & (swept.flags.reshape(-1) == 0)
    difference = np.linalg.norm(position[ok] - swept.position.reshape(-1, 3)[ok], axis=1)
    figures.append(Figure("stream (wand sweep): trusted", 100 * np.mean(flags == 0), "%", "batch",
                          100 * np.mean(swept.flags == 0), ">= 95 %", passed=np.mean(flags == 0) >= 0.95))
    figures.append(Figure("stream vs batch: position difference 99th", 1000 * np.percentile(difference, 99), "mm",
                          target="<= 0.001 mm", passed=np.percentile(difference, 99) <= 1e-6, higher_is_better=False))

    # speed
    n = check.position.size // 3
    seconds = best_time(lambda: corrector.batch(check.position, check.quaternion, check.valid_mask), repeat=3)
    quick = PoseCorrector(table, check_ambiguity=False)
    seconds_quick = best_time(lambda: quick.batch(check.position, check.quaternion, check.valid_mask), repeat=3)
    field = table.field()
    part = check.position.reshape(-1, 3)[:2000]
    reference = best_time(lambda: invert_distortion(part, lambda p: field.evaluate(p)[0]), repeat=1)
    figures.append(Figure("pose-only correction, batched", n / seconds, "frames/s", "NumPy inversion",
                          len(part) / reference, ">= 100000 frames/s", passed=n / seconds >= 1e5))
    figures.append(Figure("  the same without the ambiguity test", n / seconds_quick, "frames/s", "NumPy inversion",
                          len(part) / reference))
    signal = Corrector(table)
    S = dipole.signal_from_pose(v[:500], rotations.from_matrix(np.where(np.isfinite(Q[:500]), Q[:500], np.eye(3))))
    signal.update(S[0], sensors=names)
    signal_latency = []
    for k in range(len(S)):
        t0 = time.perf_counter()
        signal.update(S[k], sensors=names)
        signal_latency.append(time.perf_counter() - t0)
    # a 4-sensor frame (a head and hand tracker's), the target's unit: the wand's first 4 sensors
    latency4 = _stream(table, v[:, :4], Q[:, :4], names[:4])[0]
    median, median4 = float(np.median(latency)), float(np.median(latency4))
    figures.append(Figure("pose-only streaming, median per 4-sensor frame", 1e6 * median4, "us",
                          f"the same {len(names)}-sensor frames", 1e6 * median, "<= 100 us", passed=median4 <= 1e-4,
                          higher_is_better=False))
    figures.append(Figure(f"pose-only streaming, median per {len(names)}-sensor frame", 1e6 * median, "us",
                          "signal path update", 1e6 * float(np.median(signal_latency)), higher_is_better=False))
    figures.append(Figure("pose-only fit (ivc fit, 100k x 8 sweep)", fitted, "s", higher_is_better=False))
    return figures
