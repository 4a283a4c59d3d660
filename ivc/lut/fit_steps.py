"""The steps every fit path shares (:func:`ivc.lut.fit_lut`): decimating the sweep, refusing a sweep too few
of whose samples passed the gates, and the table's provenance."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from ivc import __version__
from ivc.files import file_digest
from ivc.lut.options import MIN_KEPT_FRACTION, MIN_SAMPLES
from ivc.session import Session, SessionError

__all__ = ["ADVICE", "check_enough", "decimated", "provenance"]

#: what to redo when most samples fail a gate (the signal path's gates, :data:`ivc.fixtures.mapping.DROP_REASONS`)
ADVICE = {
    "invalid sample": "the sweep's samples are mostly invalid (dropped or saturated): redo `ivc collect wand_sweep`",
    "sensor 0 invalid": "wand sensor 0 was mostly invalid: redo `ivc collect wand_sweep`",
    "not converged": "sensor 0's pose did not converge in the cube: check `ivc fixtures` and redo cube_survey or "
                     "wand_sweep",
    "outside the cube": "sensor 0 was mostly outside the cube: redo `ivc collect wand_sweep` keeping wand sensor 0 "
                        "inside the cube",
    "residual too high": "the cube field does not explain sensor 0's signal (rms(Λ) too high): redo "
                         "`ivc collect cube_survey` (and check the declared cube pose), or raise the gate "
                         "(max_residual=)",
    "estimated error too high": "the estimated sample errors exceed the gate: redo `ivc collect wand_calibration` and "
                                "`ivc collect wand_sweep` more slowly, or raise the gate (max_error=)",
}


def decimated(session: Session, max_frames: int) -> tuple[Session, int, int]:
    """``session`` with its wand sweep cut to every ``stride``-th frame, the fewest strides that keep at most
    ``max_frames``; also the frames recorded and the stride."""
    recorded = session.steps["wand_sweep"].n_frames
    stride = max(1, -(-recorded // max_frames))
    if stride > 1:
        session = session.select_frames("wand_sweep", slice(None, None, stride))
    return session, recorded, stride


def check_enough(kept: int, total: int, dropped: dict[str, int], reasons: tuple[str, ...],
                 advice: dict[str, str], recorded: int | None = None, stride: int = 1) -> None:
    """Refuse a sweep of which fewer than MIN_SAMPLES samples, or MIN_KEPT_FRACTION of them, passed the gates,
    naming the gate (of ``reasons``, in their order) that dropped most and its ``advice``; or, when the gates kept
    their share and the sweep is only too short (``recorded`` frames, every ``stride``-th solved), saying so."""
    if kept >= MIN_SAMPLES and kept >= MIN_KEPT_FRACTION * total:
        return
    if kept >= MIN_KEPT_FRACTION * total:  # the gates are not the cause: too few samples were solved
        if recorded is not None and stride > 1:
            raise SessionError(f"only {total} wand samples were solved (every {stride}-th of the sweep's {recorded} "
                               f"frames) and {kept} passed the gates; the fit needs at least {MIN_SAMPLES}: solve "
                               "more of the sweep's frames (a larger max_frames=N)")
        raise SessionError(f"the sweep holds {total} wand samples and {kept} passed the gates; the fit needs at least "
                           f"{MIN_SAMPLES}: record a longer sweep (`ivc collect wand_sweep`)")
    reason = max(reasons, key=lambda k: dropped.get(k, 0))
    detail = ", ".join(f"{n} {k}" for k, n in dropped.items() if n)
    raise SessionError(f"only {kept} of {total} wand samples passed the gates (dropped: {detail}); need at least "
                       f"{max(MIN_SAMPLES, int(MIN_KEPT_FRACTION * total))}. Most were dropped as {reason!r}: "
                       f"{advice[reason]}")


def provenance(parameters: dict, source: str | Path | None = None, fixtures: dict | None = None) -> dict:
    """The table's provenance: ivc's version, the time (UTC), the fit's ``parameters``, the ``fixtures`` it was
    mapped through (if any) and the ``source`` session's file with its SHA-256 (if given)."""
    record = {"ivc_version": __version__, "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
              "parameters": parameters}
    if fixtures is not None:
        record["fixtures"] = fixtures
    if source is not None:
        record.update(input=str(source), input_sha256=file_digest(source))
    return record
