"""A general CSV of (known rig motion, signal) rows, for tracker calibration on any precision rig.

One row per point, with a header (docs/tracker.md, "Other rigs")::

    x,y,z,qw,qx,qy,qz,s00,s01,s02,s10,s11,s12,s20,s21,s22[,source_qw,source_qx,source_qy,source_qz]

``x, y, z`` and ``qw..qz`` are the rig's known motion of the sensor side (``J_st`` of the
pose chain ``P = F_so · J_so · F_st · J_st · F_se``): metres, or ``x_mm``/``x_cm``/``x_in``
columns; a unit quaternion ``[w, x, y, z]``. ``sij`` is the signal of sensor coil ``i`` from
source coil ``j``, any unit. The optional ``source_q*`` columns are a known rotation of the
source (``J_so``; identity when absent). Bad rows are reported with their line numbers.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ivc import rotations
from ivc.errors import CsvError
from ivc.units import LENGTH_UNITS

__all__ = ["RIG_SIGNAL_COLUMNS", "read_rig_csv", "write_rig_csv"]

RIG_SIGNAL_COLUMNS = [f"s{i}{j}" for i in range(3) for j in range(3)]
_QUATERNION = ["qw", "qx", "qy", "qz"]
_SOURCE = [f"source_{c}" for c in _QUATERNION]


def _position_columns(header: list[str]) -> tuple[list[str], float]:
    for unit, scale in (("", 1.0), *((f"_{u}", s) for u, s in LENGTH_UNITS.items())):
        names = [f"{c}{unit}" for c in "xyz"]
        if all(n in header for n in names):
            return names, scale
    raise CsvError("the header needs x,y,z (metres) or x_mm,y_mm,z_mm (or _cm, _in, _m)")


def read_rig_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``S`` (N, 3, 3), ``J_so`` (N, 4, 4) and ``J_st`` (N, 4, 4) (metres) of a rig CSV."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            rows = list(csv.reader(handle))
    except UnicodeDecodeError:
        raise CsvError(f"{path}: not a text file, so not a rig CSV (a header row, then one row per point)") from None
    if not rows:
        raise CsvError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    try:
        position, scale = _position_columns(header)
    except CsvError as error:
        raise CsvError(f"{path}: {error}") from None
    missing = [c for c in _QUATERNION + RIG_SIGNAL_COLUMNS if c not in header]
    if missing:
        raise CsvError(f"{path}: missing columns {', '.join(missing)}")
    has_source = all(c in header for c in _SOURCE)
    wanted = position + _QUATERNION + RIG_SIGNAL_COLUMNS + (_SOURCE if has_source else [])
    index = [header.index(c) for c in wanted]
    values, bad = [], []
    for number, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        try:
            numbers = [float(row[k]) for k in index]
        except (ValueError, IndexError):
            bad.append(number)
            continue
        if not np.all(np.isfinite(numbers)):
            bad.append(number)
            continue
        values.append(numbers)
    if bad:
        shown = ", ".join(map(str, bad[:10])) + (" ..." if len(bad) > 10 else "")
        raise CsvError(f"{path}: {len(bad)} rows with missing or non-numeric values (lines {shown}); nothing read")
    if not values:
        raise CsvError(f"{path}: no data rows")
    a = np.array(values)
    q = a[:, 3:7]
    norms = np.linalg.norm(q, axis=1)
    off = np.flatnonzero(np.abs(norms - 1) > 1e-6)
    if len(off):
        raise CsvError(f"{path}: line {off[0] + 2}: qw,qx,qy,qz is not a unit quaternion (norm {norms[off[0]]:.6g})")
    J_st = np.zeros((len(a), 4, 4))
    J_st[:, :3, :3] = rotations.to_matrix(q)
    J_st[:, :3, 3] = a[:, :3] * scale
    J_st[:, 3, 3] = 1.0
    J_so = np.broadcast_to(np.eye(4), J_st.shape).copy()
    if has_source:
        qs = a[:, 16:20]
        off = np.flatnonzero(np.abs(np.linalg.norm(qs, axis=1) - 1) > 1e-6)
        if len(off):
            raise CsvError(f"{path}: line {off[0] + 2}: source_qw..source_qz is not a unit quaternion")
        J_so[:, :3, :3] = rotations.to_matrix(qs)
    return a[:, 7:16].reshape(-1, 3, 3), J_so, J_st


def write_rig_csv(path: str | Path, S: np.ndarray, J_st: np.ndarray, J_so: np.ndarray | None = None) -> None:
    """Write points in the rig CSV layout (positions in metres, 17 significant digits)."""
    q = rotations.from_matrix(J_st[:, :3, :3])
    columns = ["x", "y", "z", *_QUATERNION, *RIG_SIGNAL_COLUMNS] + (_SOURCE if J_so is not None else [])
    blocks = [J_st[:, :3, 3], q, np.asarray(S).reshape(-1, 9)]
    if J_so is not None:
        blocks.append(rotations.from_matrix(np.broadcast_to(J_so, J_st.shape)[:, :3, :3]))
    data = np.concatenate(blocks, axis=1)
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for row in data:
            writer.writerow([repr(float(v)) for v in row])
