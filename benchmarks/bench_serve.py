"""A PLUS user's whole protocol over OpenIGTLink (issue 36): the default scene served as PLUS serves a tracker
(``ivc serve sim --poses-only``: a TRANSFORM per sensor, no signals), collected by guided collection through the
``igtl://`` source, fitted from the reported poses and scored on the check poses.

Baseline in the same run: the same simulated protocol (seed 0, 100,000-frame sweep, 10,000 check poses) with its
signals removed, fitted and scored straight from memory (the file path, ``benchmarks.run pose_only``). Target:
the medians and the trusted share within 5 % of the file path's. The stream is lossless (a rehearsal waits for
its client), as fast as the collector reads it; the truth of the check poses is taken from the simulation, since
a tracker sends none.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

from benchmarks.harness import Figure
from ivc.app.serve import IgtlServer
from ivc.collect.guide import collect_protocol
from ivc.collect.igtl import IgtlSource
from ivc.collect.stream import SessionSource
from ivc.correct.evaluate import evaluate
from ivc.lut import fit_lut
from ivc.session import STEPS, Session
from ivc.sim import Simulator, load_scene

#: the streamed protocol must score within this share of the file path
TOLERANCE = 0.05


def _protocol() -> Session:
    scene = load_scene("default")
    simulated = Simulator(scene, seed=0).protocol()
    simulated.hemisphere = scene.hemisphere
    return simulated


def _poses_only(session: Session) -> Session:
    return Session(session.hemisphere, {name: replace(step, signal=None) for name, step in session.steps.items()},
                   dict(session.truth), dict(session.attrs))


def _streamed(simulated: Session) -> tuple[Session, float, int]:
    """The protocol served over OpenIGTLink (poses only) and collected through igtl:// by guided collection."""
    source = SessionSource(simulated, pause_s=0.5, realtime=True, speed=float("inf"))
    server = IgtlServer(source, 0, signals=False, lossless=True, start_on_connect=True)
    stop = threading.Event()
    thread = threading.Thread(target=server.run, kwargs={"stop": stop}, daemon=True)
    thread.start()
    survey = simulated.steps["cube_survey"].attrs
    start = time.perf_counter()
    with IgtlSource("127.0.0.1", server.address[1]) as client:
        collected, _ = collect_protocol(client, STEPS, hemisphere=simulated.hemisphere,
                                        declared_position=survey["declared_position"],
                                        declared_quaternion=survey["declared_quaternion"])
    seconds = time.perf_counter() - start
    stop.set()
    thread.join(30)
    server.close()
    collected.truth = dict(simulated.truth)  # the tracker sends no truth: the simulation's, for scoring
    return collected, seconds, sum(step.n_frames for step in collected.steps.values())


def _score(session: Session) -> dict:
    return evaluate(fit_lut(session), session)


def run() -> list[Figure]:
    simulated = _protocol()
    baseline = _score(_poses_only(simulated))
    collected, seconds, frames = _streamed(simulated)
    streamed = _score(collected)
    figures = [Figure("igtl protocol: frames collected", frames, "frames", "simulated",
                      sum(step.n_frames for step in simulated.steps.values()), "all",
                      passed=frames == sum(step.n_frames for step in simulated.steps.values())),
               Figure("igtl protocol: stream + collection time", seconds, "s", higher_is_better=False)]
    for label, kind in (("position median", "position_mm"), ("orientation median", "orientation_mrad")):
        value, base = streamed["ivc"][kind]["p50"], baseline["ivc"][kind]["p50"]
        unit = "mm" if kind == "position_mm" else "mrad"
        figures.append(Figure(f"igtl protocol: {label}", value, unit, "file path", base,
                              f"<= {1 + TOLERANCE:g}x file path", passed=value <= (1 + TOLERANCE) * base,
                              higher_is_better=False))
    trusted = 100 * streamed["corrected"] / streamed["samples"]
    base_trusted = 100 * baseline["corrected"] / baseline["samples"]
    figures.append(Figure("igtl protocol: trusted", trusted, "%", "file path", base_trusted,
                          f">= {1 - TOLERANCE:g}x file path", passed=trusted >= (1 - TOLERANCE) * base_trusted))
    return figures
