"""Reader of CMU ILEMT calibration recordings (``so<A>_se<B>_<pattern>.dat``), docs/tracker.md.

One row per motion-stage pose, tab- (or comma-) separated: stage X, Y, Z (mm), Rx, Ry,
Rz (degrees, ``R = Rz Ry Rx``), then 9 complex high-carrier and 9 complex low-carrier
couplings written like ``+a+bi`` (a value without an imaginary part is real). The nine
values are a column-major ``C(source coil, sensor coil)``; ivc's signal matrix (row =
sensor coil, column = source coil) is ``Cᵀ``.
A complex coupling becomes real as ``sign(Re C) · |C|`` (the real part is in phase
with the reference taken at home, the imaginary part is a small quadrature residue).

The sensor pose in source coordinates is ``P = F_so · J_so · F_st · J_st · F_se``:
``J_so`` is the source-fixture rotation named in the file name, ``J_st`` the stage
motion (after the stage's measured error compensation, :func:`compensate_stage`) times
the sensor-fixture rotation; the three ``F`` are unknown constants a calibration fits
(:mod:`ivc.pose.calibrate`). This module returns ``J_so`` and ``J_st`` as 4x4
homogeneous transforms in metres.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ivc.errors import CsvError, InputError

__all__ = ["FIXTURES", "OPTIONS_FILE", "SOURCE_SIGN_FIXES", "IlemtRecording", "compensate_stage", "fixture_rotation",
           "folder_sign_fixes", "parse_sign_fix", "read_ilemt", "real_coupling", "stack", "stage_transforms"]

#: fixture code -> the mover axes that lie along fixture +Y ("out") and fixture +Z ("up")
FIXTURES = {
    "YoutZup": ((0, 1, 0), (0, 0, 1)),
    "ZinYup": ((0, 0, -1), (0, 1, 0)),
    "ZinXdown": ((0, 0, -1), (-1, 0, 0)),
    "XoutZup": ((1, 0, 0), (0, 0, 1)),
    "ZoutYup": ((0, 0, 1), (0, 1, 0)),
    "XinYup": ((-1, 0, 0), (0, 1, 0)),
}

#: the source-coil sign fixes the ILEMT authors list for the ``cal_9_15_premo_cmu`` set only (its
#: phase reference was taken in the wrong fixture for these files; their ``local_cal_options.m``):
#: file-name pattern -> sign per source coil. A property of that data set: the reader applies
#: it only when told (``sign_fixes=SOURCE_SIGN_FIXES``, ``--sign-fix``, the folder's options file).
SOURCE_SIGN_FIXES = (
    (r"soZoutYup_seYoutZup_(md|ld)\.dat$", (-1.0, -1.0, 1.0)),
    (r"soXoutZup_seYoutZup_md\.dat$", (-1.0, -1.0, 1.0)),
)

#: a folder's own reading options (TOML), next to its recordings: ``[[sign_fix]]`` tables with
#: ``files`` (a regular expression searched in the file name), ``source`` and optionally ``sensor``
#: (a sign per coil)
OPTIONS_FILE = "ivc-ilemt.toml"

_NAME = re.compile(r"so(?P<source>[A-Za-z]+)_se(?P<sensor>[A-Za-z]+)_(?P<pattern>.+)\.dat$")
_NUMBER = r"[0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?"
_COMPLEX = re.compile(rf"^([+-]?{_NUMBER})(?:([+-]{_NUMBER})i)?$")

# Measured errors of the ILEMT motion stage (MacLachlan et al., the ILEMT calibration paper;
# tabulated in the authors' compensate_stage.m): (from axis, to axis) -> rows of
# (from-axis position mm, to-axis error mm). The error is added to the commanded position,
# shifted so that it is zero where the from-axis position is zero.
_STAGE_ERRORS = {
    (2, 0): ((50, 0.1), (40, 0.088), (30, 0.085), (20, 0.085), (10, 0.07), (0, 0.05), (-10, 0.025),
             (-20, -0.01), (-30, -0.05), (-40, -0.108), (-46, -0.14)),
    (2, 2): ((49, -0.130), (29, -0.115), (4, -0.090), (-21, -0.050), (-46, 0.0)),
    (0, 0): ((50, 0.0), (25, 0.040), (0, 0.040), (-25, 0.050), (-50, 0.155)),
    (1, 1): ((50, 0.0), (25, -0.130), (0, -0.200), (-5, -0.230), (-10, -0.135), (-15, -0.155),
             (-20, -0.257), (-25, -0.310), (-50, -0.350)),
}


def _interp_extrap(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation through (xp, fp), extrapolated linearly past both ends."""
    order = np.argsort(xp)
    xp, fp = xp[order], fp[order]
    y = np.interp(x, xp, fp)
    lo, hi = x < xp[0], x > xp[-1]
    y[lo] = fp[0] + (x[lo] - xp[0]) * (fp[1] - fp[0]) / (xp[1] - xp[0])
    y[hi] = fp[-1] + (x[hi] - xp[-1]) * (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])
    return y


def compensate_stage(stage: np.ndarray) -> np.ndarray:
    """Stage poses (N, 6) [mm, degrees] with the stage's measured axis errors added.

    Each table gives an error along one axis against the position of another; the errors
    are summed, zero at the zero position, and their XY part is turned by the stage's Rz
    (the XY errors are measured in the rotating stage's frame).
    """
    stage = np.asarray(stage, dtype=float)
    errors = np.zeros((len(stage), 3))
    for (src, dst), table in _STAGE_ERRORS.items():
        tab = np.asarray(table, dtype=float)
        values = _interp_extrap(np.concatenate([[0.0], stage[:, src]]), tab[:, 0], tab[:, 1])
        errors[:, dst] += values[1:] - values[0]
    rz = np.radians(stage[:, 5])
    c, s = np.cos(rz), np.sin(rz)
    out = stage.copy()
    out[:, 0] += c * errors[:, 0] - s * errors[:, 1]
    out[:, 1] += s * errors[:, 0] + c * errors[:, 1]
    out[:, 2] += errors[:, 2]
    return out


def fixture_rotation(code: str) -> np.ndarray:
    """Rotation (3, 3) whose columns 2 and 3 are the mover axes along fixture "out" (+Y) and "up" (+Z)."""
    if code not in FIXTURES:
        raise InputError(f"unknown ILEMT fixture code {code!r}; known: {', '.join(FIXTURES)}")
    out, up = (np.asarray(v, dtype=float) for v in FIXTURES[code])
    return np.stack([np.cross(out, up), out, up], axis=1)


def _euler_zyx(angles_deg: np.ndarray) -> np.ndarray:
    """R = Rz Ry Rx of (N, 3) angles in degrees (Rx, Ry, Rz)."""
    a = np.radians(angles_deg)
    cx, sx = np.cos(a[:, 0]), np.sin(a[:, 0])
    cy, sy = np.cos(a[:, 1]), np.sin(a[:, 1])
    cz, sz = np.cos(a[:, 2]), np.sin(a[:, 2])
    R = np.empty((len(a), 3, 3))
    R[:, 0, 0] = cz * cy
    R[:, 0, 1] = cz * sy * sx - sz * cx
    R[:, 0, 2] = cz * sy * cx + sz * sx
    R[:, 1, 0] = sz * cy
    R[:, 1, 1] = sz * sy * sx + cz * cx
    R[:, 1, 2] = sz * sy * cx - cz * sx
    R[:, 2, 0] = -sy
    R[:, 2, 1] = cy * sx
    R[:, 2, 2] = cy * cx
    return R


def stage_transforms(stage: np.ndarray, sensor_fixture: str) -> np.ndarray:
    """``J_st`` (N, 4, 4), metres: the stage pose (mm, degrees, R = Rz Ry Rx) times the sensor-fixture rotation."""
    stage = np.asarray(stage, dtype=float)
    J = np.zeros((len(stage), 4, 4))
    J[:, :3, :3] = _euler_zyx(stage[:, 3:6]) @ fixture_rotation(sensor_fixture).T
    J[:, :3, 3] = stage[:, :3] * 1e-3
    J[:, 3, 3] = 1.0
    return J


def real_coupling(C: np.ndarray) -> np.ndarray:
    """Signed magnitude ``sign(Re C) · |C|`` of complex couplings (insensitive to a small phase error)."""
    C = np.asarray(C)
    return np.where(np.real(C) < 0, -1.0, 1.0) * np.abs(C)


@dataclass
class IlemtRecording:
    """One ILEMT ``.dat`` file.

    ``stage`` (N, 6) commanded stage poses [mm, degrees]; ``stage_compensated`` the same
    with the measured stage errors added; ``coupling`` (N, 3, 3) complex ``C(source,
    sensor)`` of the chosen carrier with the sign fixes applied (``source_signs``,
    ``sensor_signs``, (3,) each; ones when none was asked for); ``signal`` (N, 3, 3) the
    real signal matrix ``sign(Re C)|C|`` transposed (row = sensor coil); ``J_so`` (4, 4)
    and ``J_st`` (N, 4, 4) the known transforms of the pose chain (metres); ``home``
    (N,) marks the rows at the stage's zero pose (the first and the last, a drift check).
    """

    path: Path
    source_fixture: str
    sensor_fixture: str
    pattern: str
    carrier: str
    stage: np.ndarray
    stage_compensated: np.ndarray
    coupling: np.ndarray
    signal: np.ndarray
    source_signs: np.ndarray
    J_so: np.ndarray
    J_st: np.ndarray
    home: np.ndarray
    sensor_signs: np.ndarray = field(default_factory=lambda: np.ones(3))

    @property
    def n_points(self) -> int:
        return len(self.stage)

    def to_step(self, fixtures=None, hemisphere: str = "+y"):
        """This recording as a session :class:`~ivc.session.Step` of one sensor, and its truth.

        The signals go in as they are (ILEMT's units; ``--tracker-model`` or
        :func:`ivc.collect.apply_tracker` brings them to ideal units). The known stage poses
        are kept in the step's attributes (``stage_poses``, mm and degrees, compensated);
        with the rig's fitted ``fixtures`` (:class:`ivc.pose.calibrate.Fixtures`) the
        chain's poses become the step's :class:`~ivc.session.Truth`, else the truth is None.
        Rows have no time stamps: ``time`` is the row number (s) at 1 Hz.
        """
        from ivc import rotations
        from ivc.session import Step, Truth

        n = self.n_points
        step = Step(time=np.arange(n, dtype=float), signal=self.signal[:, None].copy(), valid=np.ones((n, 1), bool),
                    sample_rate_hz=1.0, sensor_ids=["sensor"],
                    description=f"ILEMT recording {self.path.name} ({self.carrier} carrier)",
                    attrs={"ilemt_file": self.path.name, "source_fixture": self.source_fixture,
                           "sensor_fixture": self.sensor_fixture, "pattern": self.pattern,
                           "stage_poses": self.stage_compensated})
        if fixtures is None:
            return step, None
        from ivc.pose.calibrate import chain

        P = chain(fixtures, self.J_so, self.J_st)
        return step, Truth(P[:, None, :3, 3].copy(), rotations.from_matrix(P[:, None, :3, :3]))

    @property
    def drift(self) -> float:
        """Largest |ΔC| between the first and the last home rows, relative to the largest |C| there."""
        if not (self.home[0] and self.home[-1]):
            return float("nan")
        first, last = self.signal[0], self.signal[-1]
        return float(np.abs(first - last).max() / np.abs(first).max())


def _parse_complex(token: str, where: str) -> complex:
    m = _COMPLEX.match(token)
    if m is None:
        raise CsvError(f"{where}: {token!r} is not a complex value written like +a+bi")
    return complex(float(m.group(1)), float(m.group(2) or 0.0))


def _signs(value, where: str) -> tuple[float, float, float]:
    try:
        signs = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        signs = ()
    if len(signs) != 3 or any(v not in (-1.0, 1.0) for v in signs):
        raise InputError(f"{where}: a sign fix is three signs, one per coil, each 1 or -1; got {value!r}")
    return signs


def parse_sign_fix(text: str) -> tuple:
    """``PATTERN=sx,sy,sz`` (source coils) or ``PATTERN=sx,sy,sz/tx,ty,tz`` (then sensor coils) as a sign
    fix entry ``(pattern, source signs[, sensor signs])``; PATTERN is a regular expression searched in
    the file name."""
    pattern, sep, signs = text.rpartition("=")
    if not sep or not pattern:
        raise InputError(f"sign fix {text!r}: write PATTERN=sx,sy,sz (e.g. 'soZoutYup_seYoutZup_md=-1,-1,1')")
    try:
        re.compile(pattern)
    except re.error as error:
        raise InputError(f"sign fix {text!r}: {pattern!r} is not a regular expression ({error})") from None
    parts = signs.split("/")
    if len(parts) > 2:
        raise InputError(f"sign fix {text!r}: at most source signs and sensor signs, separated by '/'")
    return (pattern, *(_signs(part.split(","), f"sign fix {text!r}") for part in parts))


def folder_sign_fixes(folder: str | Path) -> tuple:
    """The sign fixes of a folder's options file (:data:`OPTIONS_FILE`), or ``()`` when it has none."""
    import tomllib

    path = Path(folder) / OPTIONS_FILE
    if not path.is_file():
        return ()
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"{path}: not valid TOML ({error})") from None
    fixes = []
    for k, entry in enumerate(data.get("sign_fix", [])):
        where = f"{path} sign_fix {k + 1}"
        if not isinstance(entry, dict) or not isinstance(entry.get("files"), str) or "source" not in entry:
            raise InputError(f"{where}: needs files = \"<regular expression>\" and source = [sx, sy, sz]")
        fix = (entry["files"], _signs(entry["source"], where))
        if "sensor" in entry:
            fix += (_signs(entry["sensor"], where),)
        fixes.append(fix)
    return tuple(fixes)


def _coil_signs(name: str, fixes) -> tuple[np.ndarray, np.ndarray]:
    """Source and sensor signs (3,) each of the first fix whose pattern the file name matches."""
    for fix in fixes:
        if re.search(fix[0], name):
            sensor = fix[2] if len(fix) > 2 else (1.0, 1.0, 1.0)
            return np.asarray(fix[1], dtype=float), np.asarray(sensor, dtype=float)
    return np.ones(3), np.ones(3)


def read_ilemt(path: str | Path, *, carrier: str = "high", sign_fixes=None,
               compensate: bool = True) -> IlemtRecording:
    """Read one ILEMT calibration file.

    Parameters
    ----------
    path : the ``so<A>_se<B>_<pattern>.dat`` file; A and B are fixture codes of :data:`FIXTURES`.
    carrier : ``"high"`` (columns 7-15) or ``"low"`` (columns 16-24).
    sign_fixes : entries ``(file-name regex, source signs[, sensor signs])`` (:func:`parse_sign_fix`);
        the first that matches is applied. None (default): the fixes of the folder's options
        file (:data:`OPTIONS_FILE`) if it has one, else none; ``()``: none. No fix is ever
        applied by file name alone (:data:`SOURCE_SIGN_FIXES` are one data set's, passed explicitly).
    compensate : add the stage's measured axis errors to the commanded poses (default).
    """
    path = Path(path)
    if carrier not in ("high", "low"):
        raise InputError(f"carrier must be 'high' or 'low', got {carrier!r}")
    m = _NAME.search(path.name)
    if m is None:
        raise InputError(f"{path.name}: an ILEMT file is named so<fixture>_se<fixture>_<pattern>.dat")
    for code in (m["source"], m["sensor"]):
        if code not in FIXTURES:
            raise InputError(f"{path.name}: unknown fixture code {code!r}; known: {', '.join(FIXTURES)}")
    rows = []
    with open(path, encoding="ascii", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            if not line.strip():
                continue
            fields = line.replace(",", " ").split()
            where = f"{path.name} line {number}"
            if len(fields) != 24:
                raise CsvError(f"{where}: {len(fields)} fields, expected 24 (6 stage values, 18 complex couplings)")
            try:
                stage = [float(v) for v in fields[:6]]
            except ValueError:
                raise CsvError(f"{where}: the first six fields must be stage X Y Z (mm) Rx Ry Rz (degrees)") from None
            rows.append((stage, [_parse_complex(v, where) for v in fields[6:]]))
    if not rows:
        raise CsvError(f"{path.name}: no data rows")
    stage = np.array([r[0] for r in rows])
    values = np.array([r[1] for r in rows])
    if not (np.all(np.isfinite(stage)) and np.all(np.isfinite(values))):
        raise CsvError(f"{path.name}: non-finite stage poses or couplings")
    block = values[:, :9] if carrier == "high" else values[:, 9:]
    C = block.reshape(-1, 3, 3).transpose(0, 2, 1)  # column-major: value k is C[k % 3, k // 3]
    fixes = folder_sign_fixes(path.parent) if sign_fixes is None else sign_fixes
    signs, sensor_signs = _coil_signs(path.name, fixes)
    C = C * signs[None, :, None] * sensor_signs[None, None, :]
    compensated = compensate_stage(stage) if compensate else stage.copy()
    J_so = np.eye(4)
    J_so[:3, :3] = fixture_rotation(m["source"])
    return IlemtRecording(
        path=path, source_fixture=m["source"], sensor_fixture=m["sensor"], pattern=m["pattern"], carrier=carrier,
        stage=stage, stage_compensated=compensated, coupling=C,
        signal=np.ascontiguousarray(np.swapaxes(real_coupling(C), 1, 2)), source_signs=signs,
        sensor_signs=sensor_signs,
        J_so=J_so, J_st=stage_transforms(compensated, m["sensor"]), home=np.all(stage == 0.0, axis=1),
    )


def stack(recordings: list[IlemtRecording]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All points of several recordings: ``S`` (N, 3, 3), ``J_so`` (N, 4, 4), ``J_st`` (N, 4, 4), file index (N,)."""
    if not recordings:
        raise InputError("no ILEMT recordings given")
    S = np.concatenate([r.signal for r in recordings])
    J_so = np.concatenate([np.broadcast_to(r.J_so, (r.n_points, 4, 4)) for r in recordings])
    J_st = np.concatenate([r.J_st for r in recordings])
    index = np.concatenate([np.full(r.n_points, k) for k, r in enumerate(recordings)])
    return S, J_so, J_st, index
