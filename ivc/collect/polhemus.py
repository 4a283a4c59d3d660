"""Polhemus Liberty logger CSVs: ``Time,w1,x1,y1,z1,w2,...,loc1_x,loc1_y,loc1_z,loc2_x,...``.

A row per poll of the tracker by the host: ``Time`` is the host's Unix time (s); per sensor ``n``
a unit quaternion ``wn,xn,yn,zn`` (scalar first, sign not canonical) and a position
``locn_x,locn_y,locn_z`` in the tracker's unit, which the file does not state (a Liberty reports
inches by default, the reader's default too). The logger writes each tracker frame several times
(about three rows per frame) and the sensors of one frame change on different rows. On reading:

* per sensor, a row that repeats that sensor's previous values exactly is not a new sample; the
  rows are then grouped into tracker frames in order: a frame ends when a sensor that already
  has a new sample in it changes again. The frame's time is that of its first new sample (the
  host's clock). A sensor with no new
  sample in a frame keeps its last value (a static sensor can repeat exactly), counted in the report;
* a position closer to the source than 70 % of that sensor's median distance over the surrounding
  31 frames is a dropout (a real Liberty reports about (0, 0, 0) for a few frames, passing through
  values in between on the way): the sample is flagged invalid, never kept as a pose;
* the host's clock is bursty (rows a few microseconds apart, then a pause of tens of milliseconds)
  while the tracker samples at a fixed rate: the frame times are the straight line fitted to the
  host's times against the frame number, and the host's largest deviation from it is reported;
* quaternions are normalised (the logger writes single precision), their sign made continuous.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from scipy.ndimage import median_filter

from ivc.collect.import_report import MAX_REPORTED, ImportReport, refuse_malformed
from ivc.errors import CsvError
from ivc.session import Step
from ivc.session.model import PLAUSIBLE_RANGE_M
from ivc.units import LENGTH_UNITS

#: a position nearer the source than this share of the sensor's running median distance is a dropout
DROPOUT_FRACTION = 0.7
#: frames in the running median of the distance
DROPOUT_WINDOW = 31
NORM_TOLERANCE = 1e-3


def _columns(header: list[str]) -> list[tuple[str, list[int]]]:
    """(sensor name, indices of w, x, y, z, loc_x, loc_y, loc_z) for every sensor the header names."""
    sensors = []
    n = 1
    while f"w{n}" in header:
        names = [f"w{n}", f"x{n}", f"y{n}", f"z{n}", f"loc{n}_x", f"loc{n}_y", f"loc{n}_z"]
        missing = [c for c in names if c not in header]
        if missing:
            raise CsvError(f"{header}: sensor {n} lacks the columns {', '.join(missing)}")
        sensors.append((str(n), [header.index(c) for c in names]))
        n += 1
    return sensors


def read_liberty_csv(path: str | Path, unit: str = "in") -> tuple[Step, ImportReport]:
    """Read a Liberty logger CSV into a step of its sensors (named 1, 2, ...) and the report of what was done.

    ``unit``: the positions' unit, one of m, cm, mm, in (default inches, the Liberty's default output).
    """
    path = Path(path)
    if unit not in LENGTH_UNITS:
        raise CsvError(f"{path}: position unit {unit!r}; use one of {', '.join(LENGTH_UNITS)}")
    with open(path, newline="", encoding="utf-8-sig") as handle:
        reader = csv.reader(handle)
        header = [h.strip() for h in next(reader, [])]
        if not header or header[0] != "Time":
            raise CsvError(f"{path}: line 1: expected a header starting Time,w1,x1,y1,z1")
        try:
            sensors = _columns(header)
        except CsvError as error:
            raise CsvError(f"{path}: line 1: {error}") from None
        errors, rows = [], []
        for line, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                errors.append(f"line {line}: {len(row)} fields, the header has {len(header)}")
            else:
                try:
                    rows.append([float(c) for c in row])
                except ValueError:
                    errors.append(f"line {line}: a field is not a number")
            if len(errors) > MAX_REPORTED:
                break
    refuse_malformed(path, errors)
    if len(rows) < 2:
        raise CsvError(f"{path}: fewer than 2 data rows")
    data = np.array(rows)
    report = ImportReport(str(path), f"Polhemus Liberty logger CSV, {len(sensors)} sensors", rows=len(data))
    S = len(sensors)
    values = np.stack([data[:, idx] for _, idx in sensors], axis=1)  # (rows, S, 7)
    if not np.all(np.isfinite(values)) or not np.all(np.isfinite(data[:, 0])):
        bad = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0]) + 2
        raise CsvError(f"{path}: line {bad}: NaN or inf; nothing imported")
    norms = np.linalg.norm(values[..., :4], axis=-1)
    off = np.abs(norms - 1.0) > NORM_TOLERANCE
    if off.any():
        r, s = np.argwhere(off)[0]
        raise CsvError(f"{path}: line {r + 2}: sensor {sensors[s][0]}'s quaternion has norm {norms[r, s]:.6g}; "
                       "expected unit quaternions")
    new = np.ones(values.shape[:2], bool)
    new[1:] = np.any(values[1:] != values[:-1], axis=-1)
    # group the new samples into tracker frames, in row order
    frame_of_row = np.empty(len(data), np.int64)
    frame, seen = 0, np.zeros(S, bool)
    for r in range(len(data)):
        if np.any(new[r] & seen):
            frame, seen = frame + 1, np.zeros(S, bool)
        seen |= new[r]
        frame_of_row[r] = frame
    F = frame + 1
    first_row = np.full(F, -1)
    sample = np.full((F, S, 7), np.nan)
    for r in np.flatnonzero(np.any(new, axis=1))[::-1]:  # backwards: the frame's first row wins its time
        first_row[frame_of_row[r]] = r
    has = np.zeros((F, S), bool)
    rows_new, sens_new = np.nonzero(new)
    sample[frame_of_row[rows_new], sens_new] = values[rows_new, sens_new]
    has[frame_of_row[rows_new], sens_new] = True
    # frames whose first row holds no new sample cannot occur (every frame starts with one)
    time = data[first_row, 0]
    carried = ~has
    for s in range(S):  # a sensor without a new sample in a frame keeps its last value
        last = np.maximum.accumulate(np.where(has[:, s], np.arange(F), 0))
        sample[:, s] = sample[last, s]
    carried[0] = False
    repeated = len(data) - int(np.sum(np.any(new, axis=1)))
    report.add(f"dropped {repeated} rows that repeat every sensor's previous values (the logger writes each "
               f"frame about {len(data) / F:.1f} times); {F} tracker frames")
    for s, (name, _) in enumerate(sensors):
        if carried[:, s].any():
            report.add(f"sensor {name}: no new sample in {int(carried[:, s].sum())} frames (its last value kept)")
    backwards = np.flatnonzero(np.diff(time) <= 0)
    if len(backwards):
        keep = np.r_[True, np.diff(np.maximum.accumulate(time)) > 0] & np.r_[True, np.diff(time) > 0]
        report.add(f"dropped {int((~keep).sum())} frames whose host time does not move forward")
        time, sample = time[keep], sample[keep]
        F = len(time)
    if F > 2:
        k = np.arange(F)
        slope, offset = np.polyfit(k, time - time[0], 1)
        fitted = time[0] + offset + slope * k
        report.add(f"frame times: a straight line through the host's times ({1.0 / slope:.6g} Hz); the host's "
                   f"clock deviates from it by up to {1e3 * np.max(np.abs(time - fitted)):.3g} ms")
        time = fitted
    if F < 2:
        raise CsvError(f"{path}: every row repeats the first one's values: the file holds one tracker frame, and a "
                       "recording needs at least two (was the tracker streaming, and the sensors connected?)")
    q = sample[..., :4] / np.linalg.norm(sample[..., :4], axis=-1, keepdims=True)
    flips = np.zeros((F, S), bool)
    flips[1:] = np.sum(q[1:] * q[:-1], axis=-1) < 0
    q = q * np.where(np.cumsum(flips, axis=0) % 2 == 1, -1.0, 1.0)[..., None]
    position = sample[..., 4:] * LENGTH_UNITS[unit]
    distance = np.linalg.norm(position, axis=-1)
    typical = float(np.median(distance))
    if typical > PLAUSIBLE_RANGE_M:
        # the unit that puts the sensors nearest a typical working distance (half a metre)
        raw = typical / LENGTH_UNITS[unit]
        likely = min(LENGTH_UNITS, key=lambda name: abs(np.log(raw * LENGTH_UNITS[name] / 0.5)))
        raise CsvError(f"{path}: read as {unit}, the sensors are {typical:.3g} m from the source at the median, "
                       f"beyond any AC tracker's range ({PLAUSIBLE_RANGE_M:g} m). The file does not state its unit: "
                       f"pass the one the tracker was set to as unit=, likely "
                       f"{likely} (a Liberty reports inches by default)")
    local = median_filter(distance, size=(DROPOUT_WINDOW, 1), mode="nearest")
    dropout = distance < DROPOUT_FRACTION * local
    for s, (name, _) in enumerate(sensors):
        if dropout[:, s].any():
            runs = int(np.sum(np.diff(np.r_[0, dropout[:, s].astype(int)]) == 1))
            report.add(f"sensor {name}: {int(dropout[:, s].sum())} samples in {runs} runs near (0, 0, 0) "
                       f"(under {100 * DROPOUT_FRACTION:g} % of its running median distance): flagged invalid "
                       "(dropouts)")
    report.add(f"positions read as {unit} (the file does not say; a Liberty reports inches by default)")
    report.frames = F
    step = Step(
        time=np.ascontiguousarray(time),
        position=np.ascontiguousarray(position),
        quaternion=np.ascontiguousarray(q),
        valid=~dropout,
        sample_rate_hz=float(f"{1.0 / np.median(np.diff(time)):.6g}"),
        sensor_ids=[name for name, _ in sensors],
        description="Polhemus Liberty recording",
        attrs={"position_unit_assumed": unit, "import_report": report.text()},
    )
    return step, report
