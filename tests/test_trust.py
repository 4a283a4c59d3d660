"""A trusted pose is an accurate pose (issue 37): the predicted precision, its gate, and the branch tests."""

from __future__ import annotations

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.correct import Corrector, PoseCorrector
from ivc.correct.flags import HIGH_RESIDUAL, LOW_PRECISION, NOT_CONVERGED, OUTSIDE
from ivc.errors import InputError
from ivc.lut.signal_noise import measure_reported_noise, measure_signal_noise
from ivc.pose.precision import pose_covariance, pose_precision, reported_pose_covariance, traces
from ivc.pose.tracker_solver import distortion, reported_pose, reported_pose_jacobian
from ivc.session import Session
from ivc.table.grid import Grid
from ivc.table.lookup import LookupTable
from tests.helpers import CENTRE, quadratic_field

SIGMA = 1e-4


def poses(rng, n, radius=0.12):
    r = CENTRE + rng.uniform(-radius, radius, (n, 3))
    return r, rotations.random(n, rng)


def test_compiled_precision_matches_the_numpy_cramer_rao_bound(exact_table, rng):
    r, q = poses(rng, 300)
    corrector = Corrector(exact_table, signal_noise=SIGMA)
    field = corrector.field
    expected = pose_precision(r, q, SIGMA, field.value_and_jacobian)
    for n in (300, 5):  # the parallel kernel and the serial one (a live frame)
        got = corrector.predict_precision(r[:n], q[:n])
        np.testing.assert_allclose(got[0], expected[0][:n], rtol=1e-9)
        np.testing.assert_allclose(got[1], expected[1][:n], rtol=1e-9)


def test_reported_pose_precision_kernel_matches_the_analytic_reference(exact_table, rng):
    """The compiled pose-path prediction against the same covariance from NumPy (the closed form's Jacobians from
    ivc.pose.tracker_solver.distortion, the table's gradient from its GridField)."""
    r, q = poses(rng, 200)
    T = rotations.to_matrix(q)
    v, C = distortion(r, quadratic_field(r))
    Q = C @ T
    corrector = PoseCorrector(exact_table, signal_noise=SIGMA)
    got = corrector.predict_precision(v, Q, r)
    g, dg, _ = corrector.field.evaluate(r)
    _, _, d_phi, d_omega, d_field = distortion(r, g.reshape(-1, 3, 3), dg.reshape(-1, 3, 3, 3), jacobian=True)
    expected = traces(reported_pose_covariance(Q, d_phi, d_omega, d_field, SIGMA))
    np.testing.assert_allclose(got[0], expected[0], rtol=1e-7)
    np.testing.assert_allclose(got[1], expected[1], rtol=1e-7)
    # the least-squares tracker's path is that reference itself
    ls = PoseCorrector(exact_table, solver="least-squares", signal_noise=SIGMA).predict_precision(v, Q, r)
    assert np.all(np.isfinite(ls[0])) and np.all(ls[0] > 0)


def test_compiled_closed_form_jacobian_matches_the_numpy_form_and_finite_differences(rng):
    """ivc.correct.reported_kernels.closed_form_jacobian (compiled) against ivc.pose.tracker_solver's NumPy
    Jacobian and against central differences of the closed form itself, in a strong field (off the free-space
    manifold, where the prediction needs it)."""
    from ivc.correct.reported_kernels import closed_form_jacobian

    r = FOLD_CENTRE + rng.uniform(-0.1, 0.1, (50, 3))
    F = dipole.field(r) + mirror_field(r)
    _, _, expected = reported_pose_jacobian(F)
    h = np.array([1.0, 0.0, 0.0])
    for n in range(len(r)):
        J = np.empty((6, 9))
        assert closed_form_jacobian(F[n], h, J)
        np.testing.assert_allclose(J, expected[n], rtol=1e-7, atol=1e-9 * np.abs(expected[n]).max())
        step = 1e-6 * np.linalg.norm(F[n])
        for d in range(9):
            E = np.zeros(9)
            E[d] = step
            (p_plus, C_plus), (p_minus, C_minus) = (reported_pose(F[n] + s * E.reshape(3, 3)) for s in (1, -1))
            B = C_plus @ C_minus.T
            turn = np.array([B[2, 1] - B[1, 2], B[0, 2] - B[2, 0], B[1, 0] - B[0, 1]]) / (4 * step)
            numeric = np.concatenate([(p_plus - p_minus) / (2 * step), turn])
            np.testing.assert_allclose(J[:, d], numeric, rtol=1e-5, atol=1e-6 * np.abs(J).max())


def test_the_closed_form_reaches_the_bound_in_free_space(rng):
    """In free space the closed form's own Jacobian (ivc.pose.tracker_solver), which the reported-pose prediction
    uses, spreads noise exactly as the Cramér-Rao covariance says (beside metal it does not: the test above)."""
    r, q = poses(rng, 200, radius=0.2)
    S = dipole.signal(r, rotations.to_matrix(q))
    _, _, J = reported_pose_jacobian(S)
    spread = J @ np.swapaxes(J, -1, -2)
    bound = pose_covariance(r, q, 1.0)
    np.testing.assert_allclose(traces(spread)[0], traces(bound)[0], rtol=1e-6)
    np.testing.assert_allclose(traces(spread)[1], traces(bound)[1], rtol=1e-6)


def test_reported_pose_scatter_beside_metal_is_the_solvers_not_the_free_space_bound(rng):
    """Beside metal the signal is not a free-space field, and the closed form spreads its noise wider than the
    free-space bound at the pose it reports. Monte Carlo at poses in the folded room's strong field: the
    prediction (the solver's Jacobian at the field the sensor is in) matches the scatter of the corrected
    positions; the free-space bound at the reported pose falls short."""
    grid = Grid(FOLD_CENTRE - 0.15, 0.03, (11, 11, 11))
    table = LookupTable(grid, mirror_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3),
                        np.ones(grid.shape, bool), np.full(grid.shape, 100))
    corrector = PoseCorrector(table, signal_noise=SIGMA, max_precision=None, check_ambiguity=False)
    r = FOLD_CENTRE + np.array([[0.04, 0.1, 0.0], [0.03, -0.1, 0.06], [0.04, -0.06, 0.1]])  # outside the fold
    T = rotations.to_matrix(rotations.random(len(r), rng))
    S0 = dipole.signal(r, T, mirror_field(r))
    v0, Q0 = reported_pose(S0)
    predicted = corrector.predict_precision(v0, Q0, r)[0]
    free_space = traces(pose_covariance(v0, rotations.from_matrix(Q0), SIGMA))[0]
    for n in range(len(r)):
        v, Q = reported_pose(S0[n] + SIGMA * rng.standard_normal((4000, 3, 3)))
        scatter = np.sqrt(np.trace(np.cov(v.T)))  # of the reported positions, to set the scale below
        out = corrector.batch(v, rotations.from_matrix(Q))
        spread = np.sqrt(np.trace(np.cov(out.position.T)))  # about the mean: the table's own error is a bias
        assert spread == pytest.approx(predicted[n], rel=0.05), (n, spread, predicted[n])
        assert scatter > 1.15 * free_space[n]  # the free-space bound at the reported pose is not the scatter


@pytest.mark.parametrize("path", ["signals", "reported poses"])
def test_predicted_precision_matches_the_simulated_error(exact_table, rng, path):
    """Monte Carlo: single-frame errors of noisy measurements against their prediction. A 3-D Gaussian error's
    median length over its RMS is 0.67-0.89 (from one axis to isotropic); the issue's band is 0.7-1.4."""
    r, q = poses(rng, 3000)
    T = rotations.to_matrix(q)
    S = dipole.signal(r, T, quadratic_field(r)) + SIGMA * rng.standard_normal((len(r), 3, 3))
    if path == "signals":
        out = Corrector(exact_table, signal_noise=SIGMA, max_precision=None).batch(S)
    else:
        v, Q = reported_pose(S)
        out = PoseCorrector(exact_table, signal_noise=SIGMA, max_precision=None).batch(v, rotations.from_matrix(Q))
    ok = out.flags == 0
    assert ok.mean() > 0.99
    ratio = np.linalg.norm(out.position[ok] - r[ok], axis=1) / out.precision[ok]
    assert 0.7 <= np.median(ratio) <= 1.0, np.median(ratio)
    assert np.mean(ratio > 5) < 1e-3


def test_the_default_gate_flags_only_poses_predicted_worse_than_0_8_mm(exact_table, rng):
    r, q = poses(rng, 500, radius=0.2)
    S = dipole.signal(r, rotations.to_matrix(q), quadratic_field(r))
    gated = Corrector(exact_table, signal_noise=3e-3).batch(S)
    open_ = Corrector(exact_table, signal_noise=3e-3, max_precision=None).batch(S)
    assert 0 < np.mean(open_.precision > 0.8e-3) < 1  # some poses are that imprecise with this much noise
    np.testing.assert_array_equal(gated.flags, open_.flags | np.where(open_.precision > 0.8e-3, LOW_PRECISION, 0))
    good = Corrector(exact_table, signal_noise=SIGMA).batch(S)  # where the precision is good: no flag changes
    np.testing.assert_array_equal(good.flags, Corrector(exact_table, precision=False).batch(S).flags)


def test_the_signal_noise_is_measured_from_reported_poses_alone(small_session):
    _, session = small_session
    from_signals = measure_signal_noise(session)
    poses_only = Session(session.hemisphere, {k: s.__class__(**{**s.__dict__, "signal": None})
                                              for k, s in session.steps.items()})
    from_poses = measure_reported_noise(poses_only)
    assert from_poses.source == "reported poses" and from_signals.source == "signals"
    assert from_poses.sigma == pytest.approx(from_signals.sigma, rel=0.1)
    assert measure_signal_noise(poses_only).sigma == from_poses.sigma  # the fit's measurement falls back to it


# --- the map's other branch ------------------------------------------------------------------------------------

#: the folded room's tracker noise per signal entry: the default scene's
NOISE = 6.5e-4
#: the middle of the folded room's table
FOLD_CENTRE = np.array([0.45, 0.0, 0.0])


def mirror_field(r):
    """A conductor's image source behind the volume: strong enough that the reported-pose map folds."""
    return 0.05 * dipole.field(r - np.array([0.9, 0.0, 0.0])) @ np.diag([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def folded():
    grid = Grid(FOLD_CENTRE - 0.15, 0.03, (11, 11, 11))
    values = mirror_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3)
    table = LookupTable(grid, values, np.ones(grid.shape, bool), np.full(grid.shape, 100))
    corrector = PoseCorrector(table, signal_noise=NOISE)
    rng = np.random.default_rng(3)
    r = FOLD_CENTRE + rng.uniform(-0.14, 0.14, (3000, 3))
    v, C = distortion(r, mirror_field(r))
    q = rotations.from_matrix(C @ rotations.to_matrix(rotations.random(len(r), rng)))
    out = corrector.batch(v, q)
    return table, corrector, r, v, q, out, corrector.last_ambiguous.copy()


def reported_at(r, rng):
    v, C = distortion(r, mirror_field(r))
    return v, rotations.from_matrix(C @ rotations.to_matrix(rotations.random(len(r), rng)))


def test_a_pose_the_map_produces_twice_is_flagged(folded):
    _, _, r, _, _, out, ambiguous = folded
    error = np.linalg.norm(out.position - r, axis=1)
    # solved in the mapped volume, on the other branch
    wrong = (error > 2e-3) & ((out.flags & (OUTSIDE | NOT_CONVERGED)) == 0)
    assert wrong.sum() > 20 and ambiguous.sum() > 20
    caught = out.flags != 0
    # this room folds the map far harder than any built-in scene (a fifth of its volume is contested); here
    # the search misses two percent of the wrong branches (benchmarks/bench_trust.py: none on those scenes)
    assert np.mean(caught[wrong]) >= 0.98
    assert np.all(out.flags[ambiguous] & HIGH_RESIDUAL)


def test_a_track_keeps_its_branch_and_a_stream_that_starts_there_is_flagged(folded):
    table, corrector, r, _, _, out, ambiguous = folded
    rng = np.random.default_rng(4)
    right = np.flatnonzero(ambiguous & (np.linalg.norm(out.position - r, axis=1) < 1e-3))
    assert len(right) > 5
    kept = 0
    for end in r[right[:10]]:
        # a path into the contested place from an uncontested one nearby
        for direction in rotations.random(20, rng)[:, 1:]:
            start = end + 0.03 * direction / np.linalg.norm(direction)
            v0, q0 = reported_at(start[None], rng)
            first = corrector.batch(v0, q0)
            if first.flags[0] == 0 and np.linalg.norm(first.position[0] - start) < 1e-3:
                break
        else:
            continue
        path = start + np.linspace(0, 1, 61)[:, None] * (end - start)
        v, q = reported_at(path, rng)
        tracked = corrector.track(v[:, None], q[:, None])
        if not np.all(tracked.flags == 0):
            continue  # the path crossed a fold the tracker cannot follow (flagged, not wrong)
        kept += 1
        np.testing.assert_allclose(tracked.position[:, 0], path, atol=1e-3)  # the continuing track kept its branch
        stream = PoseCorrector(table, signal_noise=NOISE)  # the same, live
        frames = [stream.update(v[k][None], rotations.to_matrix(q[k])[None], sensors=["s"]) for k in range(len(v))]
        assert all(f.flags[0] == 0 for f in frames)
        np.testing.assert_allclose(frames[-1].position[0], end, atol=1e-3)
        # a stream (and a recorded track) that starts at the contested pose is flagged: nothing decides its branch
        late = PoseCorrector(table, signal_noise=NOISE)
        assert late.update(v[-1][None], rotations.to_matrix(q[-1])[None], sensors=["s"]).flags[0] & HIGH_RESIDUAL
        assert corrector.track(v[-1:, None], q[-1:, None]).flags[0, 0] & HIGH_RESIDUAL
    assert kept >= 3


def folded_bodies(corrector, r, ambiguous, rng):
    """Three-sensor bodies in the folded room: sensor 0 where its reported pose alone is ambiguous, the other two
    where the map places them uniquely. Returns the body, its layout and mounting, and per frame the true positions
    (F, 3, 3), the reported positions (F, 3, 3) and quaternions (F, 3, 4)."""
    from ivc.fixtures.wand import WandCalibration

    layout = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.0, 0.035, 0.0]])
    mounted = rotations.random(3, rng)
    calibration = WandCalibration.from_poses(layout, mounted)
    frames = []
    for truth in np.repeat(r[ambiguous], 4, axis=0):
        T0 = rotations.to_matrix(rotations.random(1, rng))
        position, rotation = calibration.propagate(truth[None], T0)
        v, C = distortion(position[0], mirror_field(position[0]))
        q = rotations.from_matrix(C @ rotation[0])
        alone = corrector.batch(v, q)
        if alone.flags[0] & HIGH_RESIDUAL and np.all(alone.flags[1:] == 0) and np.all(
                np.linalg.norm(alone.position[1:] - position[0, 1:], axis=1) < 1e-3):
            frames.append((position[0], v, q))
        if len(frames) == 8:
            break
    assert len(frames) >= 5
    return calibration, layout, mounted, *(np.stack([f[k] for f in frames]) for k in range(3))


def test_a_rigid_body_decides_the_branch_of_a_sensor_its_reported_pose_leaves_ambiguous(folded, rng):
    """Sensor 0 of a three-sensor body sits where the map folds (its reported pose alone is ambiguous), the other
    two where it does not: the body puts sensor 0 on its true branch, and nothing is trusted off the truth."""
    from ivc.correct.rigid import agree_with_body, decide_with_body

    _, corrector, r, _, _, _, ambiguous = folded
    calibration, _, _, true_position, v, q = folded_bodies(corrector, r, ambiguous, rng)
    body = corrector.batch(v, q)
    assert np.all(body.flags[:, 0] & HIGH_RESIDUAL)
    assert not agree_with_body(body, calibration).any()
    decided = decide_with_body(corrector, v, q, body, calibration)
    assert decided[:, 0].sum() >= len(v) - 1 and not decided[:, 1:].any()
    np.testing.assert_array_equal(body.flags[decided], 0)
    trusted = body.flags == 0
    # on the true branch: within the table's own error there (the folded room's grid is coarse), as the batch's
    assert np.all(np.linalg.norm(body.position[trusted] - true_position[trusted], axis=1) < 2e-3)
    # with its other sensors untrusted the body has nothing to decide with
    lone = corrector.batch(v, q)
    lone.flags[:, 1:] = HIGH_RESIDUAL
    assert not decide_with_body(corrector, v, q, lone, calibration).any()
    with pytest.raises(InputError, match="reported positions"):
        decide_with_body(corrector, v[:, :2], q, body, calibration)


def test_correct_file_and_the_live_loop_let_a_rigid_body_decide(folded, rng, tmp_path):
    """The same bodies through ``correct_file(..., rigid_body=...)`` (a CSV of reported poses) and a live round:
    sensor 0 trusted where the body decides it, flagged without the body."""
    import json
    import socket

    from ivc.app.correct import CorrectOptions, correct_file
    from ivc.collect.replay import write_csv
    from ivc.correct.rigid import agree_with_body, decide_with_body
    from ivc.live import LiveCorrector
    from ivc.lut import write as write_lut
    from ivc.session import Step

    table, corrector, r, _, _, _, ambiguous = folded
    calibration, layout, mounted, _, v, q = folded_bodies(corrector, r, ambiguous, rng)
    body = corrector.batch(v, q)
    agree_with_body(body, calibration)
    decided = decide_with_body(corrector, v, q, body, calibration)
    assert decided[:, 0].sum() >= len(v) - 1
    F = len(v)
    write_csv(Step(time=np.arange(F) / 240.0, position=v, quaternion=q), tmp_path / "tool.csv")
    write_lut(table, tmp_path / "lut.h5")
    (tmp_path / "tool.json").write_text(json.dumps({"positions": layout.tolist(), "quaternions": mounted.tolist()}))
    plain = correct_file(tmp_path / "lut.h5", tmp_path / "tool.csv", tmp_path / "plain.csv",
                         CorrectOptions(signal_noise=NOISE))
    bodied = correct_file(tmp_path / "lut.h5", tmp_path / "tool.csv", tmp_path / "bodied.csv",
                          CorrectOptions(signal_noise=NOISE, rigid_body=tmp_path / "tool.json"))
    assert np.all(plain.corrections["tool.csv"].flags[:, 0] & HIGH_RESIDUAL)
    np.testing.assert_array_equal(bodied.corrections["tool.csv"].flags[:, 0] == 0, decided[:, 0])
    names = ["s0", "s1", "s2"]
    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(table), listener.getsockname(), ("127.0.0.1", 0), sensors=names,
                         pose_corrector=PoseCorrector(table, signal_noise=NOISE), background_compile=False,
                         rigid_body=calibration)
    try:
        Q = rotations.to_matrix(q)
        for f in range(F):
            live.pose_corrector.reset()  # each frame a new place: no track continues
            before = live.stats.flagged
            live._correct_round([(name, 1000.0 + f, None, (v[f, n], Q[f, n])) for n, name in enumerate(names)])
            assert live.stats.flagged - before == (0 if decided[f, 0] else 1)
    finally:
        live.close()
        listener.close()


def test_a_pose_whose_truth_lies_in_a_hole_of_the_map_is_flagged(folded):
    """A true position in an unmapped hole whose reported pose a mapped region also produces: the mapped-only search
    sees no rival and trusts the wrong branch; the hole search (an equivalent-source table's model over its unmapped
    nodes) finds the truth's region and flags it. A polynomial table gets no hole search (its values off the data
    are an extrapolation)."""
    table, corrector, r, v, q, out, ambiguous = folded
    grid, nodes = table.grid, table.grid.nodes()
    rng = np.random.default_rng(5)
    right = np.flatnonzero(ambiguous & (np.linalg.norm(out.position - r, axis=1) < 1e-3))
    for centre in r[right]:
        hole = np.linalg.norm(nodes - centre, axis=-1) < 0.05
        truths = centre + rng.uniform(-0.012, 0.012, (200, 3))
        v_t, q_t = reported_at(truths, rng)
        kinds = {}
        for method in ("harmonic", "equivalent sources, joint"):
            holed = LookupTable(grid, table.values, ~hole, table.support, fit={"method": method})
            c = PoseCorrector(holed, signal_noise=NOISE)
            kinds[method] = (c, c.batch(v_t, q_t))
        polynomial, sources = kinds["harmonic"][1], kinds["equivalent sources, joint"][1]
        wrong = (polynomial.flags == 0) & (np.linalg.norm(polynomial.position - truths, axis=1) > 2e-3)
        if wrong.sum() >= 10:
            break
    else:
        pytest.fail("no hole of the folded room hides a branch: the test's premise does not hold")
    assert kinds["harmonic"][0].holes is None
    assert kinds["equivalent sources, joint"][0].holes is not None
    trusted = sources.flags == 0
    assert not np.any(np.linalg.norm(sources.position[trusted] - truths[trusted], axis=1) > 2e-3)
    assert np.all(sources.flags[wrong] & HIGH_RESIDUAL)  # flagged as a pose the map does not produce uniquely
    # where the polynomial table's answer was right, the hole search changes nothing it did not have to
    fine = (polynomial.flags == 0) & ~wrong
    np.testing.assert_allclose(sources.position[fine & trusted], polynomial.position[fine & trusted])


def room_poses(room: str, folded, exact_table, rng):
    """A room's table, its tracker noise (None: not known) and reported positions (n, 3) and quaternions (n, 4):
    the folded room's check poses, or 2,000 poses in a quiet one (the exact table's)."""
    if room == "folded":
        table, _, _, v, q, _, _ = folded
        return table, NOISE, v, q
    r, T = poses(rng, 2000)
    v, C = distortion(r, exact_table.field()(r))
    return exact_table, None, v, rotations.from_matrix(C @ rotations.to_matrix(T))


@pytest.mark.parametrize("room", ["folded", "quiet"])
def test_skipping_the_nearest_start_where_nothing_folds_changes_no_result(folded, exact_table, rng, monkeypatch, room):
    """The ambiguity test skips the nearest probe's start where no partner, rival candidate or far linear start shows
    a fold: every output equals the test that always takes it, in the folded room and in a quiet one."""
    from ivc.correct import reported

    table, noise, v, q = room_poses(room, folded, exact_table, rng)
    skipping = PoseCorrector(table, signal_noise=noise)
    out = skipping.batch(v, q)
    monkeypatch.setattr(reported, "QUIET_SKIP", False)
    full = PoseCorrector(table, signal_noise=noise).batch(v, q)
    for name in ("position", "quaternion", "flags", "residual", "precision"):
        np.testing.assert_array_equal(getattr(out, name), getattr(full, name))
    assert np.all(out.iterations <= full.iterations)
    if room == "quiet":  # where nothing folds, the start is skipped (the folded room takes it nearly everywhere)
        assert out.iterations.sum() < 0.9 * full.iterations.sum()


@pytest.mark.parametrize("room", ["folded", "quiet"])
def test_a_search_that_comes_back_to_the_solution_stops_and_changes_no_result(folded, exact_table, rng, monkeypatch,
                                                                               room):
    """The ambiguity test's searches stop where they come back to within RETURNED of the solution found: every output
    but the iteration count equals that of searches run to the end, and they take fewer iterations."""
    from ivc.correct import reported_kernels

    table, noise, v, q = room_poses(room, folded, exact_table, rng)
    stopping = PoseCorrector(table, signal_noise=noise)
    out = stopping.batch(v, q)
    full = PoseCorrector(table, signal_noise=noise)
    invert = full._invert
    monkeypatch.setattr(full, "_invert", lambda *a, known=None, **k: invert(*a, **k))  # no solution known
    to_the_end = full.batch(v, q)
    for name in ("position", "quaternion", "flags", "residual", "precision"):
        np.testing.assert_array_equal(getattr(out, name), getattr(to_the_end, name))
    assert np.all(out.iterations <= to_the_end.iterations)
    if room == "folded":  # where the map folds the test searches nearly everywhere (a quiet room: hardly at all)
        assert out.iterations.sum() < 0.95 * to_the_end.iterations.sum()
    # the kernel itself: a search started beside the solution it knows stops within RETURNED of it, unconverged
    n = min(len(v), 200)
    solved = np.isfinite(out.position[:n, 0]) & (out.flags[:n] == 0)
    at = np.ascontiguousarray(v[:n][solved])
    known = np.ascontiguousarray(out.position[:n][solved])
    start = known + 2e-4
    eye = np.broadcast_to(np.eye(3), (len(at), 3, 3))
    r2, _, miss, converged, iterations, _ = stopping._invert(at, start, eye, False, known=known)
    assert len(at) > 10 and np.all(np.linalg.norm(r2 - known, axis=1) <= reported_kernels.RETURNED)
    r3, _, _, converged3, iterations3, _ = stopping._invert(at, start, eye, False)
    assert np.all(converged3) and np.all(iterations <= iterations3) and np.sum(iterations) < np.sum(iterations3)


def test_a_signal_noise_no_tracker_has_is_refused(exact_table):
    from ivc.errors import InputError

    with pytest.raises(InputError, match="normalised dipole units"):
        Corrector(exact_table, signal_noise=1e9)
    with pytest.raises(InputError, match="normalised dipole units"):
        PoseCorrector(exact_table, signal_noise=2.0)
