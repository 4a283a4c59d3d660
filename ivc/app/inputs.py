"""What an input file is, told by its content (never by its extension alone), and the checks the app functions
and commands make of their inputs before any work.

* :func:`file_kind`: a look-up table, a session, a tracker model, a recording CSV, a rig CSV, another program's
  recording or a PLUS sequence, read from the file's first bytes, its HDF5 root attributes or its CSV header.
* :func:`corrected_by`: whether a file is ivc's own corrected output (a session's ``corrected_with`` attribute or
  its steps' ``flags`` datasets; a CSV's ``flags`` and ``residual`` columns; a PLUS sequence's ``...Ivc``
  transforms). Corrected poses fed back to ``ivc correct`` are corrected twice (issue 41: 73 mm further, median):
  :func:`refuse_corrected` refuses them unless ``allow_corrected=True``.
* :func:`expect_kind`: refuse a file of another kind than the one asked for, naming what it is.
* :func:`check_rate`: a sample rate inside :data:`RATE_RANGE_HZ`.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

from ivc.errors import InputError, OptionsError

#: the sample rates (Hz) a tracker stream may be given: a stage recording without time stamps is read at 1 Hz (one
#: row a second, ILEMT's), the fastest AC trackers report a few thousand frames a second; beyond, a rate is a typing
#: slip (and a predictor's horizon in frames grows with it)
RATE_RANGE_HZ = (0.1, 10_000.0)
#: what h5py raises on a damaged file (its readers say what is wrong with it)
_UNREADABLE = (OSError, KeyError, RuntimeError, ValueError, TypeError)
#: a file's first bytes that say it is HDF5
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"

TABLE, SESSION, TRACKER = "look-up table", "session", "tracker model"
RECORDING, RIG, FOREIGN, PLUS = "recording CSV", "rig CSV", "recording in another program's format", "PLUS sequence"
#: what makes each kind, said in the messages
MADE_BY = {TABLE: "`ivc fit` writes one", SESSION: "`ivc collect` writes one", TRACKER: "`ivc tracker calibrate` "
           "writes one", RECORDING: "docs/session-format.md", RIG: "docs/tracker.md, 'Other rigs'",
           FOREIGN: "a head-orientation trace or a Polhemus Liberty logger CSV", PLUS: "PLUS's .igs.mha or .igs.nrrd"}
#: the columns a corrected recording CSV carries (ivc.app.correct)
CORRECTED_COLUMNS = ("flags", "residual")


def _head(path: Path, size: int = 4096) -> bytes:
    with open(path, "rb") as handle:
        return handle.read(size)


def _hdf5_kind(path: Path) -> str | None:
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            found = h5.attrs.get("ivc_format")
    except _UNREADABLE:  # a damaged file: its reader says what is wrong
        return None
    found = found.decode() if isinstance(found, bytes) else found
    return {"lut": TABLE, "session": SESSION}.get(str(found))


def _header(path: Path) -> list[str]:
    """The first line of a text file as CSV cells (lower case, stripped); [] when it is not text."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            return [cell.strip().lower() for cell in next(csv.reader(handle), [])]
    except (UnicodeDecodeError, csv.Error):
        return []


def file_kind(path: str | os.PathLike) -> str | None:
    """What ``path`` holds, from its content: :data:`TABLE`, :data:`SESSION`, :data:`TRACKER`, :data:`RECORDING`,
    :data:`RIG`, :data:`FOREIGN` or :data:`PLUS`; None for anything else (or a file that cannot be read)."""
    from ivc.collect.import_report import sniff

    path = Path(path)
    try:
        head = _head(path)
    except OSError:
        return None
    if head.startswith(HDF5_SIGNATURE):
        return _hdf5_kind(path)
    if head.startswith(b"NRRD") or b"ObjectType" in head[:512]:
        return PLUS
    if head.lstrip().startswith(b"{"):
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            return None
        return TRACKER if isinstance(data, dict) and data.get("format") == "ivc-tracker" else None
    if sniff(path) is not None:
        return FOREIGN
    header = set(_header(path))
    if {"time", "sensor"} <= header or {"time_ms", "sensor"} <= header:
        return RECORDING
    if {"qw", "qx", "qy", "qz", "s00", "s22"} <= header:
        return RIG
    return None


def corrected_by(path: str | os.PathLike, kind: str | None = None) -> str | None:
    """How ``path`` shows it is ivc's corrected output ("its attribute corrected_with = ...", "its columns flags,
    residual"), or None when it is not (``kind``: :func:`file_kind`'s answer, when already known)."""
    path = Path(path)
    kind = kind or file_kind(path)
    if kind == SESSION:
        try:
            return _session_corrected_by(path)
        except _UNREADABLE:  # a damaged session: its reader says what is wrong
            return None
    if kind == RECORDING:
        header = _header(path)
        if all(c in header for c in CORRECTED_COLUMNS):
            return f"its columns {', '.join(CORRECTED_COLUMNS)}"
        return None
    if kind == PLUS:
        text = _head(path, 1 << 16).decode("latin-1")
        if "IvcTransform" in text:
            return "its ...IvcTransform frame fields"
    return None


def _session_corrected_by(path: Path) -> str | None:
    import h5py

    with h5py.File(path, "r") as h5:
        if "corrected_with" in h5.attrs:
            return f"its attribute corrected_with = {_text(h5.attrs['corrected_with'])}"
        steps = h5.get("steps")
        for name, step in (steps.items() if isinstance(steps, h5py.Group) else ()):
            if "corrected_with" in step.attrs:
                return f"its step {name}'s attribute corrected_with = {_text(step.attrs['corrected_with'])}"
            if isinstance(step, h5py.Group) and "flags" in step:
                return f"its step {name}'s correction flags"
    return None


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def refuse_corrected(path: str | os.PathLike, allow: bool, keyword: str = "input_file",
                     kind: str | None = None) -> None:
    """:class:`OptionsError` when ``path`` is ivc's corrected output and ``allow`` is False: its poses were
    corrected already, and a second correction moves them again (by about the distortion once more)."""
    if allow:
        return
    how = corrected_by(path, kind)
    if how:
        raise OptionsError(f"{keyword} {path} is ivc's corrected output ({how}): correcting it again would correct "
                           "its poses twice. Give the recording as measured; or, if this file's poses really are "
                           "uncorrected, pass allow_corrected=True")


def expect_kind(path: str | os.PathLike, wanted: tuple[str, ...], keyword: str) -> str | None:
    """``path``'s kind (:func:`file_kind`); :class:`InputError` when it is a known kind not in ``wanted``, naming
    what the file is and what was asked for. An unrecognised file passes (its reader says what is wrong)."""
    kind = file_kind(path)
    if kind is not None and kind not in wanted:
        asked = " or ".join(f"a {w}" for w in wanted)
        if kind == FOREIGN:
            advice = "make it a session step first (`ivc collect STEP --source replay:FILE`)"
        elif kind == RECORDING and RIG in wanted:
            advice = ("its poses are the tracker's own reports, each with a time and a sensor; a rig CSV holds the "
                      "rig's known motion of each point (x,y,z,qw,qx,qy,qz and s00..s22, no time or sensor column)")
        else:
            advice = "check the order of the files"
        raise InputError(f"{keyword} {path} is a {kind} ({MADE_BY[kind]}), not {asked}: {advice}")
    return kind


def check_correct_inputs(lut_file: str | os.PathLike, input_file: str | os.PathLike,
                         allow_corrected: bool = False) -> None:
    """The inputs of :func:`ivc.correct_file`, before any work: ``lut_file`` a table, ``input_file`` a session,
    a recording CSV or a PLUS sequence, and not ivc's corrected output unless ``allow_corrected``."""
    expect_kind(lut_file, (TABLE,), "lut_file")
    kind = expect_kind(input_file, (SESSION, RECORDING, PLUS), "input_file")
    refuse_corrected(input_file, allow_corrected, "input_file", kind)


def check_rate(rate_hz: float | None, keyword: str = "rate_hz") -> float | None:
    """``rate_hz`` (None passes) if it is a finite rate inside :data:`RATE_RANGE_HZ`; else :class:`OptionsError`."""
    if rate_hz is None:
        return None
    low, high = RATE_RANGE_HZ
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise OptionsError(f"{keyword}={rate_hz!r} is not a number (Hz)") from None
    if not (math.isfinite(rate) and low <= rate <= high):
        raise OptionsError(f"{keyword}={rate:g} Hz is outside the sample rates of a tracker stream, {low:g} to "
                           f"{high:g} Hz")
    return rate


__all__ = ["CORRECTED_COLUMNS", "FOREIGN", "PLUS", "RATE_RANGE_HZ", "RECORDING", "RIG", "SESSION", "TABLE",
           "TRACKER", "check_correct_inputs", "check_rate", "corrected_by", "expect_kind", "file_kind",
           "refuse_corrected"]
