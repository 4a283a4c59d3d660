"""Recordings in other programs' formats, read into a :class:`~ivc.session.Step` with their quirks reported.

Two formats are recognised by their first line:

* a head-orientation trace (:mod:`ivc.collect.head_trace`): ``timestamp viewpoint w x y z``;
* a Polhemus Liberty logger CSV (:mod:`ivc.collect.polhemus`): ``Time,w1,x1,y1,z1,w2,...,loc1_x,...``.

Every importer returns the step and an :class:`ImportReport` (:mod:`ivc.collect.import_report`) that
says what was read, dropped and flagged; the report's text is also kept in ``step.attrs["import_report"]``.
Nothing is dropped or flagged without a line in the report.

This module is the dispatcher: :func:`read_import` (a foreign format), :func:`read_recording` (that or
ivc's recording CSV) and :func:`replay` (any recording, a PLUS sequence or a session's step) send a file to
its reader; the readers import only the report, never the dispatcher.
"""

from __future__ import annotations

from pathlib import Path

from ivc.collect.head_trace import read_head_trace
from ivc.collect.import_report import FORMATS, MAX_REPORTED, ImportReport, refuse_malformed, sniff
from ivc.collect.plus import is_plus_sequence, read_plus
from ivc.collect.polhemus import read_liberty_csv
from ivc.collect.replay import REPLAY_DESCRIPTION, read_csv
from ivc.errors import CsvError
from ivc.session import SessionError, Step, Truth, is_recording_csv
from ivc.session import read as read_session

__all__ = ["FORMATS", "MAX_REPORTED", "ImportReport", "read_import", "read_recording", "refuse_malformed", "replay",
           "sniff"]


def read_import(path: str | Path, unit: str | None = None) -> tuple[Step, ImportReport]:
    """Read a file in one of :data:`FORMATS`; ``unit``: the position unit of a Polhemus CSV (default inches)."""
    kind = sniff(path)
    if kind == "head-trace":
        return read_head_trace(path)
    if kind == "polhemus-liberty":
        return read_liberty_csv(path, unit="in" if unit is None else unit)
    raise CsvError(f"{path}: not a head-orientation trace (header 'timestamp viewpoint w x y z') nor a Polhemus "
                   "Liberty CSV (header 'Time,w1,x1,y1,z1,...'); for ivc's own recording CSV see "
                   "docs/session-format.md")


def read_recording(path: str | Path, sample_rate_hz: float | None = None, unit: str | None = None
                   ) -> tuple[Step, ImportReport | None]:
    """Any single-step recording: a foreign format (:func:`read_import`) or ivc's recording CSV (no report)."""
    if sniff(path) is not None:
        step, report = read_import(path, unit)
        if sample_rate_hz is not None:
            step.sample_rate_hz = float(sample_rate_hz)
        return step, report
    return read_csv(path, sample_rate_hz), None


def replay(path: str | Path, step_name: str, sample_rate_hz: float | None = None) -> tuple[Step, Truth | None]:
    """A recorded step from a session file (with its truth, if any), a recording CSV or a PLUS sequence
    (``.igs.mha``, ``.seq.nrrd``, ...: :mod:`ivc.collect.plus`)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if sniff(path) is not None:  # another program's format
        return read_recording(path, sample_rate_hz)[0], None
    if is_recording_csv(path):
        return read_csv(path, sample_rate_hz), None
    if is_plus_sequence(path):
        step = read_plus(path).step
        if sample_rate_hz is not None:
            step.sample_rate_hz = sample_rate_hz
        return step, None
    source = read_session(path)
    if step_name not in source.steps:
        have = ", ".join(source.steps) or "no steps"
        raise SessionError(f"{path}: has no step {step_name!r} to replay (it has {have})")
    step = source.steps[step_name]
    step.description = REPLAY_DESCRIPTION
    if sample_rate_hz is not None:
        step.sample_rate_hz = sample_rate_hz
    return step, source.truth.get(step_name)
