"""The whole pipeline on a simulated distorted room in one call: what ``ivc demo`` runs.

    >>> import ivc
    >>> result = ivc.demo.run(sweep_frames=4000, check_frames=300)  # doctest: +SKIP
    >>> result.report["ivc"]["position_mm"]["p50"]  # doctest: +SKIP

:func:`run` simulates the protocol (the simulator's fixtures, a wand sweep and check
poses), fits the secondary-field look-up table, and corrects and evaluates the check
poses against truth. With ``folder`` it also writes the session and the table there.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from ivc import lut
from ivc import session as session_io
from ivc.correct.evaluate import evaluate
from ivc.lut.options import FitOptions, Progress
from ivc.session import Session, Step
from ivc.sim import Scene, Simulator, load_scene
from ivc.table.lookup import LookupTable

__all__ = ["DemoResult", "SESSION_NAME", "TABLE_NAME", "demo_files", "run", "without_signals"]

#: file names of the session and the table inside the demo's folder
SESSION_NAME, TABLE_NAME = "demo.h5", "demo_lut.h5"


@dataclass
class DemoResult:
    """What :func:`run` made: the simulated session, the fitted table and the evaluation.

    ``report`` is :func:`ivc.correct.evaluate.evaluate`'s summary of the check poses (errors
    in mm and mrad, IVC beside the uncorrected dipole solution). ``session_file`` and
    ``table_file`` are ``None`` unless a folder was given. ``fit_seconds``: wall time of the fit.
    While :func:`run` works, the parts not made yet are ``None``.
    """

    session_file: Path | None = None
    table_file: Path | None = None
    session: Session | None = None
    table: LookupTable | None = None
    fit_seconds: float | None = None
    report: dict | None = None


def without_signals(session: Session) -> Session:
    """The session with every step's signal matrices removed, as a tracker that reports poses only records it."""
    steps = {name: replace(step, signal=None) for name, step in session.steps.items()}
    return Session(session.hemisphere, steps, session.truth, session.attrs)


def demo_files(folder: str | Path) -> tuple[Path, Path]:
    """The session and table paths of a demo kept in ``folder``."""
    folder = Path(folder)
    return folder / SESSION_NAME, folder / TABLE_NAME


def run(scene: str | Scene = "default", *, seed: int = 0, sweep_frames: int = 100_000, check_frames: int = 10_000,
        method: str = "harmonic", folder: str | Path | None = None, force: bool = False,
        simulator: Simulator | None = None, on_step: Callable[[str, Step, Session], None] | None = None,
        fit_progress: Progress | None = None,
        on_stage: Callable[[str, DemoResult], None] | None = None, pose_only: bool = False) -> DemoResult:
    """Collect, fit and evaluate on a simulated room.

    ``scene``: a built-in scene name, a scene .toml path or a :class:`~ivc.sim.Scene`
    (ignored when a ready ``simulator`` is given). ``folder``: write ``demo.h5`` and
    ``demo_lut.h5`` there (an existing file is refused unless ``force``). Callbacks:
    ``on_step`` after each simulated step (see :meth:`Simulator.protocol`),
    ``fit_progress`` for the fit's stages, ``on_stage(name, result)`` as each of the three
    stages (``"collect"``, ``"fit"``, ``"evaluate"``) starts, with what is made so far.
    ``pose_only``: drop every step's signals after collecting (:func:`without_signals`), so the
    table is fitted, and the check poses corrected, from the reported poses alone.
    """
    if simulator is None:
        simulator = Simulator(scene if isinstance(scene, Scene) else load_scene(scene), seed)
    result = DemoResult()
    if folder is not None:
        Path(folder).mkdir(parents=True, exist_ok=True)
        result.session_file, result.table_file = demo_files(folder)
        for existing in (result.session_file, result.table_file):
            if existing.exists() and not force:
                raise FileExistsError(f"{existing} exists; pass force=True to replace it, or another folder=DIR")
    stage = on_stage or (lambda name, partial: None)
    stage("collect", result)
    result.session = simulator.protocol({"wand_sweep": sweep_frames, "check": check_frames}, on_step=on_step)
    if pose_only:
        result.session = without_signals(result.session)
    if result.session_file is not None:
        session_io.write(result.session, result.session_file, overwrite=force)
    stage("fit", result)
    fit_start = time.perf_counter()
    result.table = lut.fit_lut(result.session, FitOptions(fitter=method), source=result.session_file,
                               progress=fit_progress)
    result.fit_seconds = time.perf_counter() - fit_start
    if result.table_file is not None:
        lut.write(result.table, result.table_file, overwrite=force)
    stage("evaluate", result)
    # the corrector of the session's kind (signals or reported poses) with the table's default trust test: the
    # precision from the signal noise the fit measured (and, for reported poses, the map's own error)
    result.report = evaluate(result.table, result.session)
    return result
