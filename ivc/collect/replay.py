"""Importing a real tracker's recording: from a session file, or from the documented CSV.

CSV layout (docs/session-format.md, "Recording CSV"): a header row, then one row per
frame and sensor::

    time,sensor,x,y,z,qw,qx,qy,qz[,s00,s01,...,s22][,valid]
    time,sensor,s00,s01,s02,s10,s11,s12,s20,s21,s22[,valid]

``time`` in seconds; ``sensor`` a name; positions in metres (source frame);
quaternions ``[w, x, y, z]``; ``sij`` the signal matrix entry for sensor coil i and
source coil j; ``valid`` 1/0 (optional, default 1). Every frame (a distinct time, in
order) must list every sensor once. Bad rows are reported with their line numbers
and nothing is imported.

A tracker's own units are read as the header names them: ``time_ms`` (milliseconds),
``x_mm,y_mm,z_mm``, ``x_cm,…`` or ``x_in,…`` (a Polhemus reports inches by default), and
``az,el,roll`` in degrees instead of the quaternion: Polhemus's Euler angles, the sensor's
axes in the source frame being the columns of ``Rz(az) Ry(el) Rx(roll)``. They are
converted to seconds, metres and quaternions on reading.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ivc import rotations
from ivc.collect.import_report import MAX_REPORTED, refuse_malformed
from ivc.errors import CsvError
from ivc.session import Step
from ivc.session.model import QUATERNION_NORM_TOLERANCE
from ivc.units import LENGTH_UNITS

POSE_COLUMNS = ["x", "y", "z", "qw", "qx", "qy", "qz"]
SIGNAL_COLUMNS = [f"s{i}{j}" for i in range(3) for j in range(3)]
QUATERNION_COLUMNS = POSE_COLUMNS[3:]
#: Polhemus Euler angles (degrees): the sensor's axes are the columns of Rz(az) Ry(el) Rx(roll)
EULER_COLUMNS = ["az", "el", "roll"]
#: time columns and seconds per unit
TIME_COLUMNS = {"time": 1.0, "time_ms": 1e-3}
#: a median sensor range beyond this (m) means the positions are not in metres: AC trackers reach a few metres
MAX_MEDIAN_RANGE = 10.0
REPLAY_DESCRIPTION = "replayed tracker recording"
#: a valid sample further than this from the source (m) is refused: AC trackers reach a few metres
MAX_RANGE = 100.0
#: largest |‖q‖ − 1| of a valid quaternion (trackers print 4-6 decimals); within it quaternions are normalised
QUATERNION_TOLERANCE = 1e-3


def write_csv(step: Step, path: str | Path, extra: dict[str, np.ndarray] | None = None,
              length_unit: str = "m") -> None:
    """Write a step as a recording CSV (floats with 17 significant digits: exact round trip).

    ``extra``: more columns after ``valid``, each an (F, N) array (written with ``str``).
    ``length_unit``: the positions' unit, named in their columns (``x_in``; metres: ``x``).
    """
    extra = extra or {}
    if length_unit not in LENGTH_UNITS:
        raise CsvError(f"unknown length unit {length_unit!r}; use one of {', '.join(LENGTH_UNITS)}")
    columns = ["time", "sensor"]
    if step.position is not None:
        columns += _position_columns(length_unit) + QUATERNION_COLUMNS
    if step.signal is not None:
        columns += SIGNAL_COLUMNS
    columns.append("valid")
    columns += list(extra)
    extras = [np.asarray(v).reshape(-1) for v in extra.values()]
    F, N = step.n_frames, step.n_sensors
    blocks = [np.repeat(step.time, N)[:, None]]
    if step.position is not None:
        blocks += [step.position.reshape(-1, 3) / LENGTH_UNITS[length_unit], step.quaternion.reshape(-1, 4)]
    if step.signal is not None:
        blocks.append(step.signal.reshape(-1, 9))
    numbers = np.concatenate(blocks, axis=1)
    names = np.tile(np.asarray(step.names, dtype=object), F)
    valid = step.valid_mask.reshape(-1)
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for k in range(len(numbers)):
            row = [repr(float(v)) for v in numbers[k]]
            writer.writerow([row[0], names[k], *row[1:], "1" if valid[k] else "0", *(str(e[k]) for e in extras)])


def read_csv(path: str | Path, sample_rate_hz: float | None = None) -> Step:
    """Read a recording CSV into a :class:`Step`; raise :class:`CsvError` listing bad lines.

    UTF-8 text, with or without the byte-order mark Excel's "CSV UTF-8" writes."""
    return read_csv_columns(path, sample_rate_hz)[0]


@dataclass
class CsvColumns:
    """What a recording CSV held besides the step: ``length_unit`` of its position columns (a key of
    LENGTH_UNITS), ``extra``: its other columns, {name: (F, N) strings, as written}."""

    length_unit: str = "m"
    extra: dict[str, np.ndarray] = field(default_factory=dict)


def read_csv_columns(path: str | Path, sample_rate_hz: float | None = None) -> tuple[Step, CsvColumns]:
    """:func:`read_csv`, and the file's position unit and extra columns (kept by ``ivc correct``)."""
    path = Path(path)
    try:
        return _read_csv(path, sample_rate_hz)
    except UnicodeDecodeError as error:
        raise CsvError(f"{path}: not UTF-8 text (byte 0x{error.object[error.start]:02x} at offset {error.start} "
                       "cannot be decoded): save the file as UTF-8 (Excel: \"CSV UTF-8\")") from None
    except csv.Error as error:
        raise CsvError(f"{path}: not a readable CSV ({error})") from None


def _read_csv(path: Path, sample_rate_hz: float | None) -> tuple[Step, CsvColumns]:
    with open(path, newline="", encoding="utf-8-sig") as handle:
        reader = csv.reader(handle)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise CsvError(f"{path}: empty file") from None
        repeated = sorted({c for c in header if header.count(c) > 1})
        if repeated:
            raise CsvError(f"{path}: line 1: column {', '.join(repeated)} appears more than once")
        layout = _layout(path, header)
        wanted = layout.columns
        extra_names = [c for c in header if c not in wanted and c not in ("sensor", "valid")]
        extra_index = [header.index(c) for c in extra_names]
        extras = []
        index = [header.index(c) for c in wanted]
        sensor_col = header.index("sensor")
        valid_col = header.index("valid") if "valid" in header else None
        errors, numbers, sensors, valid, rows = [], [], [], [], []
        for line, row in enumerate(reader, start=2):
            if not row or all(not cell.strip() for cell in row):
                continue
            if len(row) != len(header):
                errors.append(f"line {line}: {len(row)} fields, the header has {len(header)}")
                continue
            try:
                values = [float(row[i]) for i in index]
            except ValueError:
                bad = next(wanted[k] for k, i in enumerate(index) if not _is_float(row[i]))
                errors.append(f"line {line}: {bad} = {row[header.index(bad)]!r} is not a number")
                continue
            flag = True
            if valid_col is not None:
                text = row[valid_col].strip().lower()
                if text not in ("1", "0", "true", "false"):
                    errors.append(f"line {line}: valid = {row[valid_col]!r}; use 1 or 0")
                    continue
                flag = text in ("1", "true")
            if flag and not all(np.isfinite(values)):
                errors.append(f"line {line}: NaN or inf in a valid sample (set valid to 0 for a dropout)")
                continue
            numbers.append(values)
            extras.append([row[i] for i in extra_index])
            rows.append(line)
            sensors.append(row[sensor_col].strip())
            valid.append(flag)
            if len(errors) > MAX_REPORTED:
                break
    refuse_malformed(path, errors)
    if not numbers:
        raise CsvError(f"{path}: no data rows")
    numbers = np.array(numbers)
    with np.errstate(all="ignore"):  # checked row by row below
        standard = layout.standard(numbers)
    valid = np.array(valid)
    if layout.has_pose:
        standard[:, 4:8] = _checked_quaternions(path, standard[:, 4:8], valid, rows, layout)
        _check_positions(path, standard[:, 1:4], valid, rows)
    step = _assemble(path, standard, sensors, valid, layout.has_pose, layout.has_signal, sample_rate_hz, rows)
    _check_range(path, step, layout)
    table = np.array(extras, dtype=object).reshape(step.n_frames, step.n_sensors, len(extra_names))
    return step, CsvColumns(layout.unit, {name: table[:, :, k] for k, name in enumerate(extra_names)})


class _Layout:
    """Which columns of a recording CSV hold what, and how to bring them to seconds, metres and quaternions."""

    def __init__(self, time: str, position: list[str], unit: str, orientation: list[str], signal: bool):
        self.time, self.position, self.unit, self.orientation = time, position, unit, orientation
        self.has_pose, self.has_signal = bool(position), signal
        self.columns = [time, *position, *orientation, *(SIGNAL_COLUMNS if signal else [])]

    def standard(self, numbers: np.ndarray) -> np.ndarray:
        """Rows of :attr:`columns` as ``time, x, y, z, qw, qx, qy, qz, s00..s22`` (s, m, unit quaternion)."""
        time = numbers[:, :1] * TIME_COLUMNS[self.time]
        parts, k = [time], 1
        if self.has_pose:
            parts.append(numbers[:, 1:4] * LENGTH_UNITS[self.unit])
            k = 4 + len(self.orientation)
            angles = numbers[:, 4:k]
            if self.orientation == EULER_COLUMNS:
                quaternion = np.full((len(numbers), 4), np.nan)
                finite = np.all(np.isfinite(angles), axis=1)
                if np.any(finite):
                    quaternion[finite] = rotations.from_scipy(Rotation.from_euler("ZYX", angles[finite], degrees=True))
                angles = quaternion
            parts.append(angles)
        parts.append(numbers[:, k:])
        return np.concatenate(parts, axis=1)

    def describe(self) -> str:
        """The position columns, as read, with their unit."""
        return f"{','.join(self.position)} ({self.unit})"


def _layout(path: Path, header: list[str]) -> _Layout:
    """The columns of ``header`` to read, or a CsvError saying what the header lacks."""
    times = [c for c in TIME_COLUMNS if c in header]
    units = [u for u in LENGTH_UNITS if all(c in header for c in _position_columns(u))]
    orientations = [c for c in (QUATERNION_COLUMNS, EULER_COLUMNS) if all(n in header for n in c)]
    has_signal = all(c in header for c in SIGNAL_COLUMNS)
    if len(header) == 1 and any(mark in header[0] for mark in ";\t"):
        mark = ";" if ";" in header[0] else "tab"
        raise CsvError(f"{path}: line 1: its columns are separated by {mark!r}: a recording CSV separates them by "
                       "commas and writes decimals with a point (0.25, not 0,25), as spreadsheets do in an English "
                       "locale; save it again that way")
    problems = []
    partial = [(name, [c for c in group if c not in header]) for name, group in
               (("signal", SIGNAL_COLUMNS), ("quaternion", QUATERNION_COLUMNS), ("Euler angle", EULER_COLUMNS),
                *((f"position ({u})", _position_columns(u)) for u in LENGTH_UNITS))]
    for name, missing in partial:
        group_size = {"signal": 9, "quaternion": 4}.get(name, 3)
        if 0 < len(missing) < group_size:
            problems.append(f"the whole set of {name} columns (missing {','.join(missing)})")
    if len(times) != 1:
        problems.append("one time column: time (s) or time_ms" + (" (not both)" if times else ""))
    if "sensor" not in header:
        problems.append("a sensor column")
    if len(units) > 1:
        problems.append("one set of position columns, not " + " and ".join(",".join(_position_columns(u))
                                                                            for u in units))
    if len(orientations) > 1:
        problems.append("one orientation: qw,qx,qy,qz or az,el,roll, not both")
    if bool(units) != bool(orientations):
        problems.append("orientation columns (qw,qx,qy,qz, or az,el,roll in degrees) with the positions"
                        if units else "position columns (x,y,z in m, or x_mm / x_cm / x_in) with the orientation")
    elif not units and not has_signal:
        problems.append(f"either poses ({','.join(POSE_COLUMNS)}) or the signal matrix ({','.join(SIGNAL_COLUMNS)})")
    if problems:
        raise CsvError(f"{path}: line 1: the header needs " + "; ".join(problems) + f"; got {','.join(header)}")
    unit = units[0] if units else "m"
    return _Layout(times[0], _position_columns(unit) if units else [], unit,
                   orientations[0] if orientations else [], has_signal)


def _position_columns(unit: str) -> list[str]:
    return [f"{axis}{'' if unit == 'm' else '_' + unit}" for axis in "xyz"]


def _check_range(path: Path, step: Step, layout: _Layout) -> None:
    """Refuse positions whose median range says they are not in the header's unit."""
    if step.position is None:
        return
    ranges = np.linalg.norm(step.position[step.valid_mask], axis=-1)
    if len(ranges) and np.median(ranges) > MAX_MEDIAN_RANGE:
        raise CsvError(
            f"{path}: the sensors' median distance from the source is {np.median(ranges):.3g} m with positions in "
            f"{layout.describe()}; AC trackers reach a few metres. If the tracker reports another unit, name it in "
            "the header: x_mm,y_mm,z_mm, x_cm,... or x_in,... (a Polhemus reports inches by default)")


def _checked_quaternions(path: Path, q: np.ndarray, valid: np.ndarray, rows: list[int], layout: _Layout) -> np.ndarray:
    """Valid samples' quaternions normalised (when off by more than the session format's tolerance); a norm
    off by more than QUATERNION_TOLERANCE (a zero quaternion, a column in the wrong place) is refused."""
    if layout.orientation == EULER_COLUMNS:
        return q
    norm = np.linalg.norm(q, axis=1)
    bad = valid & ~(np.abs(norm - 1) <= QUATERNION_TOLERANCE)
    if bad.any():
        k = int(np.argmax(bad))
        raise CsvError(f"{path}: line {rows[k]}: the quaternion qw,qx,qy,qz has norm {norm[k]:.6g}; it must be a unit "
                       f"quaternion [w, x, y, z] ({int(bad.sum())} valid rows are not; set valid to 0 for a dropout)")
    rescale = valid & (np.abs(norm - 1) > QUATERNION_NORM_TOLERANCE)  # unit ones are kept bit for bit
    return np.where(rescale[:, None], q / np.where(rescale, norm, 1.0)[:, None], q)


def _check_positions(path: Path, position: np.ndarray, valid: np.ndarray, rows: list[int]) -> None:
    """Refuse a valid sample further than MAX_RANGE from the source: no AC tracker reaches it."""
    distance = np.linalg.norm(position, axis=1)
    bad = valid & ~(distance <= MAX_RANGE)
    if bad.any():
        k = int(np.argmax(bad))
        raise CsvError(f"{path}: line {rows[k]}: the position is {distance[k]:.3g} m from the source (more than "
                       f"{MAX_RANGE:g} m): a corrupt row, or positions in another unit than the header's "
                       "(name it: x_mm, x_cm, x_in)")


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _assemble(path, numbers, sensors, valid, has_pose, has_signal, sample_rate_hz, rows) -> Step:
    names = list(dict.fromkeys(sensors))
    N = len(names)
    if len(numbers) % N:
        raise CsvError(f"{path}: {len(numbers)} rows is not a whole number of frames of {N} sensors")
    F = len(numbers) // N
    expected = np.tile(np.asarray(names, dtype=object), F)
    got = np.asarray(sensors, dtype=object)
    mismatch = np.flatnonzero(expected != got)
    if len(mismatch):
        k = mismatch[0]
        raise CsvError(
            f"{path}: line {rows[k]}: sensor {got[k]!r} where {expected[k]!r} was expected; every frame must "
            f"list the sensors {', '.join(names)} once, in the same order"
        )
    numbers = numbers.reshape(F, N, -1)
    time = numbers[:, 0, 0]
    changes = np.flatnonzero(np.any(numbers[:, :, 0] != time[:, None], axis=1))
    if len(changes):
        raise CsvError(f"{path}: line {rows[changes[0] * N]}: the sensors of one frame must share one time")
    repeated = np.flatnonzero(~(np.diff(time) > 0))
    if len(repeated):
        f = int(repeated[0]) + 1
        what = "repeats" if time[f] == time[f - 1] else "is earlier than"
        raise CsvError(f"{path}: line {rows[f * N]}: time {float(time[f])!r} s {what} the previous frame's "
                       f"({float(time[f - 1])!r} s): frames must be in time order, each time once (sort the file, "
                       "or remove the duplicates)")
    column = 1
    position = quaternion = signal = None
    if has_pose:
        position, quaternion = numbers[:, :, 1:4], numbers[:, :, 4:8]
        column = 8
    if has_signal:
        signal = numbers[:, :, column : column + 9].reshape(F, N, 3, 3)
    if sample_rate_hz is None:
        steps = np.diff(time)
        if len(steps) == 0 or np.median(steps) <= 0:
            raise CsvError(f"{path}: cannot infer the sample rate from the times; pass sample_rate_hz=HZ")
        sample_rate_hz = float(f"{1.0 / np.median(steps):.6g}")
    return Step(
        time=np.ascontiguousarray(time),
        signal=None if signal is None else np.ascontiguousarray(signal),
        position=None if position is None else np.ascontiguousarray(position),
        quaternion=None if quaternion is None else np.ascontiguousarray(quaternion),
        valid=valid.reshape(F, N),
        sample_rate_hz=sample_rate_hz,
        sensor_ids=names,
        description=REPLAY_DESCRIPTION,
    )
