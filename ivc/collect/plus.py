"""PLUS Toolkit sequence files (``.igs.mha``, ``.seq.mha``, ``.igs.nrrd``, ``.seq.nrrd``): read as a step, written back.

PLUS (and 3D Slicer's Sequences module) record tracking as a MetaImage (``.mha``) or NRRD
(``.nrrd``) header whose per-frame fields carry the poses; a file with images then holds the
pixel data after the header. Per frame ``NNNN``:

``Seq_FrameNNNN_<Tool>To<Tracker>Transform``
    16 numbers, the 4x4 homogeneous matrix row by row, translation in millimetres: the pose
    of ``<Tool>`` in the ``<Tracker>`` frame.
``Seq_FrameNNNN_<Tool>To<Tracker>TransformStatus``
    ``OK``, or ``MISSING``, ``INVALID``, ``OUT_OF_VIEW`` ...: only ``OK`` is valid (a missing
    status field counts as ``OK``, as PLUS reads it).
``Seq_FrameNNNN_Timestamp``
    seconds (PLUS's system clock); ``..._UnfilteredTimestamp`` and ``..._FrameNumber`` are kept.

:func:`read_plus` takes every ``<Tool>To<Tracker>Transform`` of the file's tracker frame (the
``To`` frame most transforms share) as one sensor: positions in metres, quaternions
``[w, x, y, z]`` of the nearest rotation, ``valid`` from the status. Transforms to other frames
are listed in :attr:`PlusSequence.other_transforms` and not imported. :func:`write_plus` writes
the file back with its header, every original field and any pixel data unchanged and new
transforms added per frame (``ivc correct``: ``<Tool>To<Tracker>Ivc``, with its status and the
correction's flags), ``CustomFrameFieldNames`` updated when the file lists its fields, and
``ElementDataFile`` last, as MetaIO requires.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ivc import rotations
from ivc.errors import SessionError
from ivc.session import Step

__all__ = ["PLUS_SUFFIXES", "PlusError", "PlusSequence", "is_plus_sequence", "read_plus", "write_plus"]

#: file names PLUS gives its sequences (the readers go by the last suffix: .mha or .nrrd)
PLUS_SUFFIXES = (".igs.mha", ".seq.mha", ".igs.nrrd", ".seq.nrrd", ".mha", ".nrrd")
#: a header longer than this (bytes) is refused: a day at 240 Hz with 10 tools is about 1.5 GB of text
MAX_HEADER_BYTES = 1 << 31
#: largest |RᵀR − I| of a transform's rotation part (PLUS prints 6 significant digits)
MAX_ORTHONORMALITY_ERROR = 1e-3
#: a translation further than this from the tracker (mm) is refused as corrupt
MAX_TRANSLATION_MM = 1e5
MM = 1e-3
PLUS_DESCRIPTION = "PLUS sequence"

_FRAME_FIELD = re.compile(r"Seq_Frame(\d+)_(.+)")
_TRANSFORM = re.compile(r"(.+?)To([A-Z0-9].*)Transform")


class PlusError(SessionError):
    """A PLUS sequence file is malformed or holds no usable transform; the message names the field."""


def is_plus_sequence(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a PLUS sequence file (MetaImage ``.mha`` or NRRD ``.nrrd``)."""
    return Path(path).suffix.lower() in (".mha", ".nrrd")


@dataclass
class PlusSequence:
    """A PLUS sequence file as read.

    ``step``: the imported sensors (see the module docstring). ``tracker``: the frame their
    poses are in. ``tools``: the ``<Tool>`` of each sensor, in order. ``frame_numbers``: PLUS's
    ``FrameNumber`` of each frame (None when absent). ``other_transforms``: transform names to
    other frames, not imported. ``header``: the fields before the frames, ``frames``: each
    frame's fields, ``trailer``: the fields after them, all as (key, value) text in file order.
    ``data``: the bytes after the header (pixel data; may be empty). ``nrrd``: the file is NRRD.
    """

    step: Step
    tracker: str
    tools: list[str]
    frame_numbers: np.ndarray | None
    other_transforms: list[str]
    header: list[tuple[str, str]]
    frames: list[list[tuple[str, str]]]
    trailer: list[tuple[str, str]]
    data: bytes = b""
    nrrd: bool = False
    unfiltered_time: np.ndarray | None = field(default=None)

    @property
    def sensor_names(self) -> list[str]:
        return [f"{tool}To{self.tracker}" for tool in self.tools]


def _split_header(path: Path, raw: bytes) -> tuple[list[tuple[str, str]], bytes, bool]:
    """The header's (key, value) fields in order, the bytes after it, and whether it is NRRD."""
    nrrd = raw.startswith(b"NRRD")
    fields: list[tuple[str, str]] = []
    at = 0
    if nrrd:
        end = raw.find(b"\n", 0) + 1
        if end == 0:
            raise PlusError(f"{path}: an NRRD file without a header")
        at = end
    while at < len(raw):
        end = raw.find(b"\n", at)
        end = len(raw) if end < 0 else end
        line_bytes = raw[at:end].rstrip(b"\r")
        at = end + 1
        if at > MAX_HEADER_BYTES:
            raise PlusError(f"{path}: header longer than {MAX_HEADER_BYTES} bytes")
        try:
            line = line_bytes.decode("utf-8")
        except UnicodeDecodeError:
            raise PlusError(f"{path}: header line {len(fields) + 1} is not text: {line_bytes[:40]!r}") from None
        if nrrd:
            if not line.strip():
                return fields, raw[at:], nrrd  # a blank line ends an NRRD header
            if line.startswith("#"):
                continue
            key, sep, value = line.partition(":=") if ":=" in line else line.partition(":")
        else:
            key, sep, value = line.partition("=")
        if not sep:
            raise PlusError(f"{path}: header line {len(fields) + 1} is not `key = value`: {line[:80]!r}")
        key, value = key.strip(), value.strip()
        fields.append((key, value))
        if not nrrd and key == "ElementDataFile":  # MetaIO: the last field; the data follow
            return fields, raw[at:], nrrd
    return fields, b"", nrrd


def _numbers(path: Path, key: str, value: str, count: int) -> np.ndarray:
    try:
        numbers = np.array([float(v) for v in value.split()])
    except ValueError:
        raise PlusError(f"{path}: {key} = {value[:80]!r}: expected {count} numbers") from None
    if numbers.shape != (count,):
        raise PlusError(f"{path}: {key}: expected {count} numbers, got {len(numbers)}")
    return numbers


def _frame_count(path: Path, header: dict[str, str], found: int) -> int:
    """Frames the header declares (DimSize or sizes: the last entry), checked against the frames found."""
    declared = header.get("DimSize", header.get("sizes"))
    if declared is None:
        return found
    try:
        count = int(declared.split()[-1])
    except (ValueError, IndexError):
        raise PlusError(f"{path}: DimSize = {declared!r}: expected whole numbers") from None
    if count != found:
        raise PlusError(f"{path}: the header declares {count} frames (DimSize {declared}) but frames 0 to "
                        f"{found - 1} are present: a truncated or edited file")
    return count


def read_plus(path: str | os.PathLike) -> PlusSequence:
    """Read a PLUS sequence file; raise :class:`PlusError` naming the field that is wrong."""
    path = Path(path)
    raw = path.read_bytes()
    fields, data, nrrd = _split_header(path, raw)
    header, trailer = [], []
    frames: dict[int, list[tuple[str, str]]] = {}
    for key, value in fields:
        match = _FRAME_FIELD.fullmatch(key)
        if match:
            frames.setdefault(int(match.group(1)), []).append((match.group(2), value))
        elif frames:
            trailer.append((key, value))
        else:
            header.append((key, value))
    if not frames:
        raise PlusError(f"{path}: no Seq_FrameNNNN_ fields: not a PLUS sequence (or one without frames)")
    indices = sorted(frames)
    if indices != list(range(len(indices))):
        gap = next(k for k, n in enumerate(indices) if n != k)
        raise PlusError(f"{path}: frame {gap:04d} is missing (frames are numbered from 0000 without gaps)")
    _frame_count(path, dict(header + trailer), len(indices))
    per_frame = [dict(frames[k]) for k in indices]
    for k, names in enumerate(frames[n] for n in indices):
        keys = [name for name, _ in names]
        if len(set(keys)) != len(keys):
            raise PlusError(f"{path}: frame {k:04d} repeats a field")
    names = list(dict.fromkeys(name for f in per_frame for name in f))
    transforms = [(n, *_TRANSFORM.fullmatch(n).groups()) for n in names if _TRANSFORM.fullmatch(n)]
    if not transforms:
        raise PlusError(f"{path}: no <Tool>To<Tracker>Transform fields: nothing to import")
    targets = [target for _, _, target in transforms]
    tracker = max(dict.fromkeys(targets), key=targets.count)
    chosen = [(n, tool) for n, tool, target in transforms if target == tracker]
    others = [n for n, _, target in transforms if target != tracker]
    F, N = len(per_frame), len(chosen)
    matrices = np.full((F, N, 4, 4), np.nan)
    valid = np.zeros((F, N), bool)
    for k, frame in enumerate(per_frame):
        for n, (name, _) in enumerate(chosen):
            value = frame.get(name)
            status = frame.get(name + "Status", "OK").strip().upper()
            if value is None:
                continue  # not recorded in this frame: invalid
            matrices[k, n] = _numbers(path, f"Seq_Frame{k:04d}_{name}", value, 16).reshape(4, 4)
            valid[k, n] = status == "OK"
    time = _times(path, per_frame, "Timestamp", required=True)
    unfiltered = _times(path, per_frame, "UnfilteredTimestamp", required=False, ordered=False)
    position, quaternion = _poses(path, matrices, valid, [name for name, _ in chosen])
    rate = 1.0 / float(np.median(np.diff(time))) if F > 1 else 1.0
    step = Step(time=time, position=position, quaternion=quaternion, valid=valid,
                sample_rate_hz=float(f"{rate:.6g}"), sensor_ids=[f"{tool}To{tracker}" for _, tool in chosen],
                description=PLUS_DESCRIPTION)
    numbers = None
    if all("FrameNumber" in f for f in per_frame):
        try:
            numbers = np.array([int(f["FrameNumber"]) for f in per_frame])
        except ValueError:
            raise PlusError(f"{path}: a FrameNumber is not a whole number") from None
    return PlusSequence(step, tracker, [tool for _, tool in chosen], numbers, others, header,
                        [frames[k] for k in indices], trailer, data, nrrd, unfiltered)


def _times(path: Path, frames: list[dict], key: str, required: bool, ordered: bool = True) -> np.ndarray | None:
    if not all(key in f for f in frames):
        if required:
            missing = next(k for k, f in enumerate(frames) if key not in f)
            raise PlusError(f"{path}: Seq_Frame{missing:04d}_{key} is missing: every frame needs its time")
        return None
    try:
        t = np.array([float(f[key]) for f in frames])
    except ValueError:
        raise PlusError(f"{path}: a {key} is not a number") from None
    if not np.all(np.isfinite(t)):
        raise PlusError(f"{path}: a {key} is NaN or inf")
    if ordered and len(t) > 1 and not np.all(np.diff(t) > 0):
        k = int(np.argmax(~(np.diff(t) > 0))) + 1
        raise PlusError(f"{path}: Seq_Frame{k:04d}_{key} = {float(t[k])!r} s is not after the previous frame's "
                        f"({float(t[k - 1])!r} s): frames must be in time order, each time once")
    return t


def _poses(path: Path, m: np.ndarray, valid: np.ndarray, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Positions (m) and quaternions of the valid matrices; invalid samples keep what they hold (or NaN)."""
    F, N = valid.shape
    position = np.full((F, N, 3), np.nan)
    quaternion = np.full((F, N, 4), np.nan)
    ok = valid & np.all(np.isfinite(m.reshape(F, N, 16)), axis=-1)
    bad_valid = valid & ~ok
    if bad_valid.any():
        k, n = np.argwhere(bad_valid)[0]
        raise PlusError(f"{path}: Seq_Frame{k:04d}_{names[n]} holds NaN or inf with status OK")
    if not ok.any():
        return position, quaternion
    R = m[ok][:, :3, :3]
    t = m[ok][:, :3, 3]
    last = m[ok][:, 3]
    error = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    problems = ~((error <= MAX_ORTHONORMALITY_ERROR) & (np.linalg.det(R) > 0)
                 & np.all(np.abs(last - [0, 0, 0, 1]) <= 1e-6, axis=1)
                 & (np.linalg.norm(t, axis=1) <= MAX_TRANSLATION_MM))
    if problems.any():
        k, n = np.argwhere(ok)[int(np.argmax(problems))]
        raise PlusError(f"{path}: Seq_Frame{k:04d}_{names[n]} is not a rigid transform (a rotation, a translation "
                        f"within {MAX_TRANSLATION_MM:g} mm and a last row 0 0 0 1) although its status is OK")
    U, _, Vt = np.linalg.svd(R)  # the nearest rotation to the 6-digit matrix
    nearest = U @ Vt
    position[ok] = t * MM
    quaternion[ok] = rotations.from_matrix(nearest)
    return position, quaternion


def _transform_text(m: np.ndarray) -> str:
    return " ".join(f"{v:.9g}" for v in m.reshape(16))


def write_plus(sequence: PlusSequence, path: str | os.PathLike,
               added: dict[str, tuple]) -> None:
    """Write ``sequence`` back to ``path`` (use :func:`ivc.session.atomic_path`) with transforms added.

    ``added``: {transform name (``<Tool>To<Frame>``): (positions (F, N) x 3 metres, quaternions (F, N, 4),
    flags (F, N) or None)} for the sequence's N sensors; a sample is ``OK`` when its pose is finite and
    its flags (if given) are 0, else ``INVALID`` (its matrix then the identity, as PLUS writes one).
    Each transform is written as ``<name>Transform`` with ``<name>TransformStatus`` and, with flags,
    ``<name>Flags`` (ivc's flags: 0 trusted; see ``ivc correct --help``). A fourth element, {field suffix: values
    (F, N)}, adds per-sample numbers as ``<name><suffix>`` (``PrecisionMm``: the predicted precision).
    """
    F = len(sequence.frames)
    new_fields: list[list[tuple[str, str]]] = [[] for _ in range(F)]
    names = []
    for name_pattern, entry in added.items():
        position, quaternion, flags = entry[:3]
        extra = entry[3] if len(entry) > 3 else {}
        position, quaternion = np.asarray(position, float), np.asarray(quaternion, float)
        if position.shape[:2] != (F, len(sequence.tools)):
            raise PlusError(f"{name_pattern}: positions of shape {position.shape}, the sequence has {F} frames of "
                            f"{len(sequence.tools)} tools")
        ok = np.all(np.isfinite(position), axis=-1) & np.all(np.isfinite(quaternion), axis=-1)
        if flags is not None:
            ok &= np.asarray(flags) == 0
        m = np.zeros((F, len(sequence.tools), 4, 4))
        m[..., :3, :3] = rotations.to_matrix(np.where(ok[..., None], quaternion, [1.0, 0.0, 0.0, 0.0]))
        m[..., :3, 3] = np.where(ok[..., None], position, 0.0) / MM
        m[..., 3, 3] = 1.0
        for n, tool in enumerate(sequence.tools):
            name = name_pattern.format(tool=tool, tracker=sequence.tracker)
            names += [f"{name}Transform", f"{name}TransformStatus"] + ([f"{name}Flags"] if flags is not None else [])
            names += [f"{name}{suffix}" for suffix in extra]
            for k in range(F):
                new_fields[k] += [(f"{name}Transform", _transform_text(m[k, n])),
                                  (f"{name}TransformStatus", "OK" if ok[k, n] else "INVALID")]
                if flags is not None:
                    new_fields[k].append((f"{name}Flags", str(int(flags[k, n]))))
                for suffix, values in extra.items():
                    new_fields[k].append((f"{name}{suffix}", f"{float(values[k, n]):.6g}"))
    existing = {key for frame in sequence.frames for key, _ in frame}
    clash = [n for n in names if n in existing]
    if clash:
        raise PlusError(f"the sequence already has {clash[0]}: ivc adds its transforms under new names only")
    sep = ":=" if sequence.nrrd else " = "
    plain = ": " if sequence.nrrd else " = "
    lines = ["NRRD0004"] if sequence.nrrd else []
    for key, value in sequence.header:
        if key == "CustomFrameFieldNames":
            value = " ".join([*value.split(), *dict.fromkeys(names)])
        lines.append(f"{key}{plain}{value}")
    for k, frame in enumerate(sequence.frames):
        for key, value in [*frame, *new_fields[k]]:
            lines.append(f"Seq_Frame{k:04d}_{key}{sep}{value}")
    trailer = [(k, v) for k, v in sequence.trailer if k != "ElementDataFile"]
    data_file = [(k, v) for k, v in sequence.trailer if k == "ElementDataFile"]
    for key, value in trailer + data_file:
        if key == "CustomFrameFieldNames":
            value = " ".join([*value.split(), *dict.fromkeys(names)])
        lines.append(f"{key}{plain}{value}")
    text = "\n".join(lines) + "\n" + ("\n" if sequence.nrrd else "")
    with open(path, "wb") as handle:
        handle.write(text.encode("utf-8"))
        handle.write(sequence.data)
