"""Head-orientation traces: ``timestamp viewpoint w x y z``, space separated (e.g. 360-degree video studies).

One sensor, orientation only: ``timestamp`` in seconds, a ``viewpoint`` index (kept as the step
attribute ``viewpoints``, a video cut rather than a head movement) and a unit quaternion, scalar
first, whose sign may flip between rows. On reading:

* rows that repeat the previous row's time are dropped, and so are rows whose time goes back
  (both counted in the report);
* a quaternion off unit norm by more than 1e-3, or not finite, is a malformed row (the file is refused
  with the line numbers); the others are normalised;
* the sign is made continuous (q and −q are one orientation), so consecutive samples differ by
  less than a half turn of the 4-D sphere;
* exact repeats of the previous orientation at a later time are kept (the predictors drop them,
  see docs/predict.md) and counted in the report.

The trace has no positions: the step's positions are 0 and its attribute ``orientation_only`` is set.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ivc.collect.import_report import MAX_REPORTED, ImportReport, refuse_malformed
from ivc.errors import CsvError
from ivc.session import Step

HEADER = ["timestamp", "viewpoint", "w", "x", "y", "z"]
#: a quaternion whose norm is off 1 by more than this is a malformed row, not a rounding
NORM_TOLERANCE = 1e-3


def read_head_trace(path: str | Path) -> tuple[Step, ImportReport]:
    """Read a head-orientation trace into a one-sensor step (sensor ``head``) and the report of what was done."""
    path = Path(path)
    errors, rows = [], []
    with open(path, encoding="utf-8-sig") as handle:
        header = handle.readline().split()
        if header != HEADER:
            raise CsvError(f"{path}: line 1: expected the header {' '.join(HEADER)!r}, got {' '.join(header)!r}")
        for line, text in enumerate(handle, start=2):
            cells = text.split()
            if not cells:
                continue
            if len(cells) != 6:
                errors.append(f"line {line}: {len(cells)} fields, expected 6")
                continue
            try:
                values = [float(c) for c in cells]
            except ValueError:
                errors.append(f"line {line}: {text.strip()!r} holds something that is not a number")
                continue
            norm = float(np.linalg.norm(values[2:]))
            if not np.all(np.isfinite(values)) or abs(norm - 1.0) > NORM_TOLERANCE:
                errors.append(f"line {line}: the quaternion has norm {norm:.6g} or is not finite; expected a unit "
                              "quaternion w x y z")
                continue
            rows.append((line, values))
            if len(errors) > MAX_REPORTED:
                break
    refuse_malformed(path, errors)
    if len(rows) < 2:
        raise CsvError(f"{path}: fewer than 2 data rows")
    report = ImportReport(str(path), "head-orientation trace (timestamp viewpoint w x y z)", rows=len(rows))
    data = np.array([v for _, v in rows])
    lines = np.array([n for n, _ in rows])
    time, viewpoint, q = data[:, 0], data[:, 1], data[:, 2:]
    keep = np.ones(len(time), bool)
    latest = -np.inf
    for k in range(len(time)):  # a running maximum: a row is kept only when its time moves forward
        if time[k] > latest:
            latest = time[k]
        else:
            keep[k] = False
    same = np.r_[False, time[1:] == time[:-1]] & ~keep
    back = ~keep & ~same
    if same.any():
        report.add(f"dropped {int(same.sum())} rows repeating the previous row's time (first at line "
                   f"{lines[same][0]})")
    if back.any():
        report.add(f"dropped {int(back.sum())} rows whose time goes back (first at line {lines[back][0]})")
    time, viewpoint, q = time[keep], viewpoint[keep], q[keep]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    flips = np.r_[False, np.sum(q[1:] * q[:-1], axis=1) < 0]
    sign = np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)
    q = q * sign[:, None]
    if flips.any():
        report.add(f"made the quaternion's sign continuous at {int(flips.sum())} rows (q and -q are one orientation)")
    repeats = int(np.sum(np.all(q[1:] == q[:-1], axis=1)))
    if repeats:
        report.add(f"{repeats} samples repeat the previous orientation exactly at a later time (kept; the "
                   "predictors drop them)")
    report.add("no positions in the file: positions are 0 (orientation only)")
    report.frames = len(time)
    steps = np.diff(time)
    step = Step(
        time=np.ascontiguousarray(time),
        position=np.zeros((len(time), 1, 3)),
        quaternion=np.ascontiguousarray(q[:, None, :]),
        valid=np.ones((len(time), 1), bool),
        sample_rate_hz=float(f"{1.0 / np.median(steps):.6g}"),
        sensor_ids=["head"],
        description="head-orientation trace",
        attrs={"orientation_only": True, "viewpoints": np.unique(viewpoint).astype(int).tolist(),
               "import_report": report.text()},
    )
    return step, report
