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
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ivc.session import SessionError, Step, Truth
from ivc.session import read as read_session

POSE_COLUMNS = ["x", "y", "z", "qw", "qx", "qy", "qz"]
SIGNAL_COLUMNS = [f"s{i}{j}" for i in range(3) for j in range(3)]
REPLAY_DESCRIPTION = "replayed tracker recording"
_MAX_REPORTED = 10


class CsvError(SessionError):
    """A recording CSV is malformed; the message lists the bad lines."""


def write_csv(step: Step, path: str | Path, extra: dict[str, np.ndarray] | None = None) -> None:
    """Write a step as a recording CSV (floats with 17 significant digits: exact round trip).

    ``extra``: more columns after ``valid``, each an (F, N) array (written with ``str``).
    """
    extra = extra or {}
    columns = ["time", "sensor"]
    if step.position is not None:
        columns += POSE_COLUMNS
    if step.signal is not None:
        columns += SIGNAL_COLUMNS
    columns.append("valid")
    columns += list(extra)
    extras = [np.asarray(v).reshape(-1) for v in extra.values()]
    F, N = step.n_frames, step.n_sensors
    blocks = [np.repeat(step.time, N)[:, None]]
    if step.position is not None:
        blocks += [step.position.reshape(-1, 3), step.quaternion.reshape(-1, 4)]
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
    """Read a recording CSV into a :class:`Step`; raise :class:`CsvError` listing bad lines."""
    path = Path(path)
    with open(path, newline="") as handle:
        reader = csv.reader(handle)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise CsvError(f"{path}: empty file") from None
        has_pose = all(c in header for c in POSE_COLUMNS)
        has_signal = all(c in header for c in SIGNAL_COLUMNS)
        if "time" not in header or "sensor" not in header or not (has_pose or has_signal):
            raise CsvError(
                f"{path}: line 1: the header needs time, sensor and either {','.join(POSE_COLUMNS)} "
                f"or {','.join(SIGNAL_COLUMNS)}; got {','.join(header)}"
            )
        wanted = ["time"] + (POSE_COLUMNS if has_pose else []) + (SIGNAL_COLUMNS if has_signal else [])
        index = [header.index(c) for c in wanted]
        sensor_col = header.index("sensor")
        valid_col = header.index("valid") if "valid" in header else None
        errors, numbers, sensors, valid = [], [], [], []
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
            sensors.append(row[sensor_col].strip())
            valid.append(flag)
            if len(errors) > _MAX_REPORTED:
                break
    if errors:
        more = " (and more)" if len(errors) > _MAX_REPORTED else ""
        raise CsvError(f"{path}: malformed rows, nothing imported{more}:\n  " + "\n  ".join(errors[:_MAX_REPORTED]))
    if not numbers:
        raise CsvError(f"{path}: no data rows")
    return _assemble(path, np.array(numbers), sensors, np.array(valid), has_pose, has_signal, sample_rate_hz)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _assemble(path, numbers, sensors, valid, has_pose, has_signal, sample_rate_hz) -> Step:
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
            f"{path}: line {k + 2}: sensor {got[k]!r} where {expected[k]!r} was expected; every frame must "
            f"list the sensors {', '.join(names)} once, in the same order"
        )
    numbers = numbers.reshape(F, N, -1)
    time = numbers[:, 0, 0]
    changes = np.flatnonzero(np.any(numbers[:, :, 0] != time[:, None], axis=1))
    if len(changes):
        raise CsvError(f"{path}: line {changes[0] * N + 2}: the sensors of one frame must share one time")
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
            raise CsvError(f"{path}: cannot infer the sample rate from the times; pass --rate")
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


def replay(path: str | Path, step_name: str, sample_rate_hz: float | None = None) -> tuple[Step, Truth | None]:
    """A recorded step from a session file (with its truth, if any) or a recording CSV."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if path.suffix.lower() == ".csv":
        return read_csv(path, sample_rate_hz), None
    source = read_session(path)
    if step_name not in source.steps:
        have = ", ".join(source.steps) or "no steps"
        raise SessionError(f"{path}: has no step {step_name!r} to replay (it has {have})")
    step = source.steps[step_name]
    step.description = REPLAY_DESCRIPTION
    if sample_rate_hz is not None:
        step.sample_rate_hz = sample_rate_hz
    return step, source.truth.get(step_name)
