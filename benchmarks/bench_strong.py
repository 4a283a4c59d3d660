"""Strong rooms (issue 38): the built-in ``severe``, ``cabinet`` (a steel cabinet 8 cm beside the mapped ball) and
``strong`` (the default room at four times its induced moments) scenes, beside the default scene.

For each scene, seed 0, the default protocol (a 100,000-frame sweep, 10,000 check poses uniform in the cube's
reach; ``IVC_BENCH_STRONG_SWEEP`` / ``IVC_BENCH_STRONG_CHECK`` set smaller counts for a quick run, and the
figures say which were used), three tables of the same session: ``ivc fit``'s default (harmonic, refined), the
adaptive fit (``ivc fit --method adaptive``, ``ivc.lut.fit_adaptive``, refined) and, from the session's reported
poses alone (its signals removed, as a tracker that gives none records it), the pose-only table ``ivc fit`` makes
of such a session. Figures of the check poses whose true position lies in the table's mapped volume:

- signals: trusted share >= 95 %; aligned median position error (after the best rigid alignment, as
  ``ivc evaluate`` reports it) <= 2x the single-frame noise floor there (the Cramér-Rao bound at the true poses,
  ``ivc.sim.noise_floor``), p99 <= 1 mm; the trusted share under the fixed residual limit of old
  (``max_residual=1e-3``) beside the default gate scaled to the table's model error (``ivc.correct.residual_gate``);
- reported poses: trusted share >= 90 %, aligned median within 1.5x the signals' (default fit); beside them the
  share of the check poses where the room's pose-domain map does not fold (``det ∂φ/∂r > 0`` in the true field),
  the most reported poses alone can trust (docs/strong-rooms.md, "Reported poses on a folded map");
- the uncorrected dipole solution and the noise floor beside;
- the share of samples the fit down-weights as outliers (all are clean: the simulator adds white noise only);
- the mapped volume within 10 % of the default scene's for the same sweep;
- the default fit of a 100,000-frame sweep <= 30 s, the adaptive fit's time beside it.

``python -m benchmarks.bench_strong [SCENE ...] [--json DIR]`` runs the given scenes (default: all, the default
scene first); with ``--json`` each scene's measurements are written to ``DIR/SCENE.json`` and a scene already
there is read instead of measured again (a long run can be made one scene at a time).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.harness import Figure
from ivc import dipole
from ivc.correct import Corrector, PoseCorrector
from ivc.correct.evaluate import check_errors
from ivc.correct.residual_gate import MAX_RESIDUAL
from ivc.errors import IvcError
from ivc.lut import FitOptions, fit_lut
from ivc.lut.joint import mapped_litres
from ivc.pose.tracker_solver import distortion
from ivc.session import Session
from ivc.sim import Simulator, load_scene
from ivc.sim.noise_floor import finite_difference_jacobian, pose_noise_floor
from ivc.sim.tracker import noise_sigma

SWEEP = int(os.environ.get("IVC_BENCH_STRONG_SWEEP", 100_000))
CHECK = int(os.environ.get("IVC_BENCH_STRONG_CHECK", 10_000))
SCENES = ("severe", "cabinet", "strong")
FITS = ("harmonic", "adaptive")
TRUSTED, POSE_TRUSTED, MEDIAN_OVER_FLOOR, POSE_MEDIAN_OVER_SIGNALS = 0.95, 0.90, 2.0, 1.5
P99_MM, VOLUME_SPREAD, FIT_SECONDS = 1.0, 0.10, 30.0


def _sessions(name: str) -> tuple[Simulator, Session, Session]:
    """The scene's simulator, its protocol with signals and the same with its signals removed."""
    simulator = Simulator(load_scene(name), seed=0)
    signals = simulator.protocol({"wand_sweep": SWEEP, "check": CHECK})
    poses = Session(signals.hemisphere, {k: replace(s, signal=None) for k, s in signals.steps.items()},
                    signals.truth, signals.attrs)
    return simulator, signals, poses


def _check(errors, table) -> dict:
    """Trusted share and aligned errors of the check poses inside ``table``'s mapped volume."""
    inside = table.field().mapped(errors.true_position[:, 0]) & errors.valid[:, 0]
    trusted = inside & errors.ok[:, 0]
    aligned = errors.aligned_position_mm[:, 0]
    some = trusted.any()  # nothing trusted (every pose flagged): no error figures
    return {"inside": int(inside.sum()), "trusted": float(trusted.sum() / max(inside.sum(), 1)),
            "median": float(np.median(aligned[trusted])) if some else float("nan"),
            "p99": float(np.percentile(aligned[trusted], 99)) if some else float("nan"),
            "max": float(np.max(aligned[trusted])) if some else float("nan"),
            "flags": {str(bit): int(np.sum((errors.flags[:, 0][inside] & bit) != 0)) for bit in (1, 2, 4, 16)},
            "trusted_mask": trusted}


def folded_share(simulator: Simulator, r: np.ndarray) -> float:
    """Share of the true positions r (n, 3) m where the room's pose-domain map turns space inside out,
    ``det ∂φ/∂r < 0`` (the true field, central differences): each such pose's reported position has another true
    position, and reported poses alone cannot tell them apart (docs/strong-rooms.md, "Reported poses on a folded
    map"), so at most the rest can be trusted from reported poses."""
    def phi(x):
        return distortion(x, simulator.secondary(x))[0]

    h = 1e-5
    J = np.stack([(phi(r + h * e) - phi(r - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    return float(np.mean(np.linalg.det(J) < 0))


def _fitted(session: Session, method: str | None) -> tuple:
    start = time.perf_counter()
    table = fit_lut(session, FitOptions() if method is None else FitOptions(fitter=method))
    return table, time.perf_counter() - start


def measure(name: str) -> dict:
    """Every figure of one scene (a json-ready dict)."""
    start = time.perf_counter()
    simulator, signals, poses = _sessions(name)
    out = {"scene": name, "sweep": SWEEP, "check": CHECK, "seed": 0, "simulated_s": time.perf_counter() - start}
    truth = signals.truth["check"]
    secondary = simulator.secondary(truth.position[:, 0])
    ratio = np.linalg.norm(secondary, axis=(1, 2)) / np.linalg.norm(dipole.field(truth.position[:, 0]), axis=(1, 2))
    floor = 1000 * pose_noise_floor(truth.position[:, 0], truth.quaternion[:, 0], noise_sigma(simulator.scene.noise),
                                    finite_difference_jacobian(simulator.secondary))[0]
    out.update(ratio_median=float(np.median(ratio)), ratio_max=float(np.max(ratio)),
               folded=folded_share(simulator, truth.position[:, 0]))
    for method in FITS:
        table, seconds = _fitted(signals, method)
        errors = check_errors(Corrector(table, signals.hemisphere), signals)
        fixed = check_errors(Corrector(table, signals.hemisphere, max_residual=MAX_RESIDUAL), signals)
        figures = _check(errors, table)
        trusted = figures.pop("trusted_mask")
        valid = errors.valid[:, 0]
        fit = table.fit
        out[method] = {
            **figures, "seconds": seconds, "floor": float(np.median(floor[trusted])),
            "trusted_fixed_gate": _check(fixed, table)["trusted"],
            "uncorrected_median": float(np.median(errors.dipole_position_mm[:, 0][valid])),
            "uncorrected_p99": float(np.percentile(errors.dipole_position_mm[:, 0][valid], 99)),
            "outliers": fit.get("outliers_downweighted", 0) / fit["samples"]["used"],
            "cv_mm": fit.get("cv_rms_mm"), "litres": mapped_litres(table.grid, table.valid),
            "choice": fit.get("model_choice", f"harmonic degree {fit.get('degree')}"),
            "gate": Corrector(table, signals.hemisphere).residual_gate.describe()}
        print(f"# {name}, {method}: fitted in {seconds:.0f} s, {out[method]['choice']}", flush=True)
    out["poses"] = _pose_only(poses)
    out["load"] = os.getloadavg()[0]
    out["total_s"] = time.perf_counter() - start
    print(f"# {name}, reported poses: {out['poses'].get('error') or 'fitted'}; scene done in {out['total_s']:.0f} s",
          flush=True)
    return out


def _pose_only(poses: Session) -> dict:
    """The pose-only table's figures, or the fit's refusal (``error``: nothing trusted)."""
    try:
        table, seconds = _fitted(poses, None)
    except IvcError as error:
        return {"error": str(error), "trusted": 0.0, "median": float("nan"), "p99": float("nan"), "flags": {},
                "seconds": float("nan")}
    errors = check_errors(PoseCorrector(table, poses.hemisphere), poses)
    figures = _check(errors, table)
    figures.pop("trusted_mask")
    valid = errors.valid[:, 0]
    return {**figures, "seconds": seconds, "litres": mapped_litres(table.grid, table.valid),
            "uncorrected_median": float(np.median(errors.dipole_position_mm[:, 0][valid])),
            "cv_mm": table.fit.get("cv_rms_mm"), "degree": table.fit.get("degree")}


def figures_of(m: dict, default: dict | None) -> list[Figure]:
    """The rows of one scene's measurements ``m`` (``default``: the default scene's, for the mapped volume)."""
    name, figures = m["scene"], []
    h, a, p = m["harmonic"], m["adaptive"], m["poses"]
    targets = name != "default"
    print(f"# {name} ({m['sweep']} sweep frames, {m['check']} check poses, seed {m['seed']}, load {m['load']:.1f}): "
          f"secondary / primary at the check poses {m['ratio_median']:.2f} median, {m['ratio_max']:.2f} max; "
          f"adaptive chose {a['choice']}; flags in the mapped volume: default fit {h['flags']}, adaptive {a['flags']}, "
          f"reported poses {p['flags']}")
    if "error" in p:
        print(f"# {name}, reported poses: the pose-only fit refused the session: {p['error']}")
    for label, f in (("ivc fit", h), ("adaptive", a)):
        other = a if f is h else h
        other_name = "adaptive" if f is h else "ivc fit"
        limit = MEDIAN_OVER_FLOOR * f["floor"]
        figures += [
            Figure(f"{name}, {label}: trusted in mapped volume", 100 * f["trusted"], "%", "fixed residual gate",
                   100 * f["trusted_fixed_gate"], f">= {100 * TRUSTED:g} %" if targets else "(reference)",
                   f["trusted"] >= TRUSTED if targets else None),
            Figure(f"{name}, {label}: aligned median", f["median"], "mm", other_name, other["median"],
                   f"<= {limit:.3g} mm (2x floor)", f["median"] <= limit, higher_is_better=False),
            Figure(f"{name}, {label}: aligned p99", f["p99"], "mm", other_name, other["p99"], f"<= {P99_MM:g} mm",
                   f["p99"] <= P99_MM, higher_is_better=False),
            Figure(f"{name}, {label}: aligned max", f["max"], "mm", other_name, other["max"], "(reference)",
                   higher_is_better=False),
            Figure(f"{name}, {label}: outliers down-weighted", 100 * f["outliers"], "%", other_name,
                   100 * other["outliers"], "(reference)", higher_is_better=False),
            Figure(f"{name}, {label}: cross-validation", f["cv_mm"], "mm", other_name, other["cv_mm"], "(reference)",
                   higher_is_better=False),
            Figure(f"{name}, {label}: fit time", f["seconds"], "s", other_name, other["seconds"],
                   f"<= {FIT_SECONDS:g} s" if f is h else "(reference)",
                   f["seconds"] <= FIT_SECONDS if f is h else None, higher_is_better=False),
        ]
        if default is not None and targets:
            spread = f["litres"] / default["harmonic"]["litres"] - 1
            figures.append(Figure(f"{name}, {label}: mapped volume", f["litres"], "litres", "default scene",
                                  default["harmonic"]["litres"], f"within {100 * VOLUME_SPREAD:g} %",
                                  abs(spread) <= VOLUME_SPREAD))
    figures += [
        Figure(f"{name}: noise floor (CRB) median", h["floor"], "mm", "uncorrected median", h["uncorrected_median"],
               "(reference)", higher_is_better=False),
        Figure(f"{name}: uncorrected p99", h["uncorrected_p99"], "mm", target="(reference)"),
        Figure(f"{name}, reported poses: trusted in mapped volume", 100 * p["trusted"], "%", "signals, ivc fit",
               100 * h["trusted"], f">= {100 * POSE_TRUSTED:g} %" if targets else "(reference)",
               p["trusted"] >= POSE_TRUSTED if targets else None),
        Figure(f"{name}, reported poses: where the map does not fold", 100 * (1 - m.get("folded", np.nan)), "%",
               target="(reference: at most this share can be trusted from reported poses)"),
        Figure(f"{name}, reported poses: aligned median", p["median"], "mm", "signals, ivc fit", h["median"],
               f"<= {POSE_MEDIAN_OVER_SIGNALS:g}x signals", p["median"] <= POSE_MEDIAN_OVER_SIGNALS * h["median"],
               higher_is_better=False),
        Figure(f"{name}, reported poses: aligned p99", p["p99"], "mm", "signals, ivc fit", h["p99"], "(reference)",
               higher_is_better=False),
        Figure(f"{name}, reported poses: fit time", p["seconds"], "s", target="(reference)", higher_is_better=False),
    ]
    return figures


def _measured(name: str, folder: Path | None) -> dict:
    path = None if folder is None else folder / f"{name}.json"
    if path is not None and path.exists():
        return json.loads(path.read_text())
    m = measure(name)
    if path is not None:
        folder.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(m, indent=1))
    return m


def run(scenes: tuple[str, ...] = ("default", *SCENES), folder: Path | None = None) -> list[Figure]:
    print(f"# strong rooms: sweep {SWEEP} frames, {CHECK} check poses, seed 0")
    measured = {name: _measured(name, folder) for name in scenes}
    default = measured.get("default") or (_measured("default", folder) if folder and (folder / "default.json").exists()
                                          else None)
    figures = []
    for m in measured.values():
        figures += figures_of(m, default)
    return figures


if __name__ == "__main__":
    import sys

    from benchmarks.harness import HEADER

    args = sys.argv[1:]
    folder = None
    if "--json" in args:
        at = args.index("--json")
        folder = Path(args[at + 1])
        args = args[:at] + args[at + 2:]
    chosen = run(tuple(args) or ("default", *SCENES), folder)
    print(HEADER)
    for figure in chosen:
        print(figure.line())
    sys.exit(1 if any(f.passed is False for f in chosen) else 0)
