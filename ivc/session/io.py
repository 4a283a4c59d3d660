"""Read and write session files (docs/session-format.md).

Every write is atomic: the new file is written beside the target under a temporary
name and renamed over it only once complete and valid, so an interrupted write
leaves the previous file as it was. A step that is already in a file is never
replaced unless the caller passes ``force=True``.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ivc.files import atomic_path  # noqa: F401 (public here before ivc.files)
from ivc.session.model import (
    FORMAT_NAME,
    FORMAT_VERSION,
    Session,
    SessionError,
    Step,
    Truth,
    step_order,
    validate_step,
)

_STEP_DATASETS = ("time", "signal", "position", "quaternion", "valid")
_STEP_ATTRS = ("sample_rate_hz", "sensor_ids", "description")
_FILE_ATTRS = ("ivc_format", "ivc_format_version", "length_unit", "hemisphere")

#: the flag bits of a corrected pose (``ivc.correct.flags``), as the ``meaning`` attribute of ``flags`` states them
FLAGS_MEANING = ("0 trusted; bits: 1 outside the mapped volume, 2 not converged, 4 residual too high (reported poses: "
                 "the map does not produce the pose, or not uniquely), 8 invalid input, 16 predicted precision over "
                 "the limit")
_PRECISION_MEANING = ("predicted RMS error of the corrected pose from the tracker's signal noise (Cramér-Rao bound of "
                      "one frame)")


@dataclass
class StepCorrection:
    """The datasets a corrected session adds to a step (docs/session-format.md, "Corrected sessions").

    ``flags`` (F, N) int: 0 for a trusted pose, else the bits of :data:`FLAGS_MEANING`; ``residual`` (F, N):
    rms(M − T S)/rms(S) of each corrected sample (reported poses: the pose-domain misfit); ``precision`` (F, N),
    metres, and ``orientation_precision`` (F, N), radians: the predicted RMS error of each corrected pose, when it
    was asked for (else None).
    """

    flags: np.ndarray
    residual: np.ndarray
    precision: np.ndarray | None = None
    orientation_precision: np.ndarray | None = None


try:
    import fcntl
except ImportError:  # Windows: no advisory locks; one writer at a time is then the user's to keep
    fcntl = None

#: how long a writer waits for another to finish with the same session file before giving up, seconds
LOCK_WAIT_S = 600.0


@contextlib.contextmanager
def writer_lock(path: str | os.PathLike, *, wait_s: float = LOCK_WAIT_S,
                on_wait: Callable[[str], None] | None = None) -> Iterator[None]:
    """Hold the one-writer lock of the file ``path`` (an advisory ``flock`` on ``.NAME.lock`` beside it).

    Read-modify-write of a session (:func:`add_step`) happens under it, so that several ``ivc collect`` writing
    steps into one session at once each add theirs instead of replacing the others'. A second writer waits for
    the first, telling ``on_wait`` once why it waits; after ``wait_s`` seconds it raises SessionError naming
    the process that holds the lock. The lock file exists only while a writer holds it (a writer that finds
    the file it locked already removed by the previous holder starts again)."""
    if fcntl is None:
        yield
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock_path = path.with_name(f".{path.name}.lock")
    deadline = time.monotonic() + wait_s
    told = False
    while True:
        handle = open(lock_path, "a+")  # noqa: SIM115 (held across the yield below)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            if time.monotonic() >= deadline:
                raise SessionError(f"{path}: {holder} has been writing this file for over {wait_s:.0f} s; "
                                   "wait for it to finish, or stop it, then try again") from None
            if on_wait is not None and not told:
                on_wait(f"{path}: waiting for {holder}, which is writing this file")
                told = True
            time.sleep(0.05)
            continue
        try:
            current = os.stat(lock_path)
        except FileNotFoundError:
            current = None
        held = os.fstat(handle.fileno())
        if current is not None and (current.st_ino, current.st_dev) == (held.st_ino, held.st_dev):
            break
        handle.close()  # the previous holder removed the file we locked: lock the new one
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"ivc process {os.getpid()}")
        handle.flush()
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(lock_path)
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


def _decode(value):
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    if isinstance(value, np.ndarray) and value.dtype.kind in "OS":
        return [v.decode(errors="replace") if isinstance(v, bytes) else str(v) for v in value.tolist()]
    return value


def _read_dataset(group: h5py.Group, name: str, required: bool = False):
    if name not in group:
        if required:
            raise SessionError(f"{group.name}/{name}: missing dataset")
        return None
    item = group[name]
    if not isinstance(item, h5py.Dataset):
        raise SessionError(f"{item.name}: expected a dataset, found a group")
    return item[()]


def is_recording_csv(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a recording CSV (docs/session-format.md, "Recording CSV") rather than an HDF5 file."""
    return Path(path).suffix.lower() == ".csv"


@contextlib.contextmanager
def open_ivc_file(path: str | os.PathLike, kind: str, version: int, what: str, error: type[SessionError] = SessionError,
                  hint: str = "") -> Iterator[tuple[h5py.File, dict]]:
    """Open an ivc HDF5 file for reading: yield the open file and its decoded root attributes.

    Raises FileNotFoundError when ``path`` does not exist, and ``error`` when it is not HDF5,
    not an ivc file of ``kind`` (``what`` names it, ``hint`` says how to make one), or of
    another format version than ``version``.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such {what}")
    try:
        handle = h5py.File(path, "r")
    except OSError as problem:
        if is_recording_csv(path):
            raise error(f"{path}: a recording CSV, not an ivc {what} (HDF5); make a session of it with `ivc collect "
                        f"STEP --source replay:{path} -o SESSION.h5`") from None
        raise error(f"{path}: not an HDF5 file ({problem})") from None
    with handle as h5:
        attrs = {key: _decode(value) for key, value in h5.attrs.items()}
        found_kind = attrs.get("ivc_format")
        if not isinstance(found_kind, str) or found_kind != kind:
            found = (f"an ivc {found_kind!r} file" if isinstance(found_kind, str) and found_kind
                     else "a file without the ivc_format attribute" if found_kind is None
                     else f"a file whose ivc_format is {found_kind!r}")
            raise error(f"{path}: not an ivc {what}: / attribute ivc_format: expected {kind!r}, this is {found}{hint}")
        try:
            found_version = int(attrs.get("ivc_format_version", -1))
        except (TypeError, ValueError):
            raise error(f"{path}: / attribute ivc_format_version = {attrs['ivc_format_version']!r}: not a whole "
                        "number") from None
        if found_version != version:
            advice = "upgrade ivc to read it" if found_version > version else "it is not a version ivc ever wrote"
            raise error(f"{path}: / attribute ivc_format_version = {found_version}: this ivc reads {version}; {advice}")
        yield h5, attrs


def read(path: str | os.PathLike) -> Session:
    """Read and validate a session file.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    SessionError
        The file is not a session file of a version this ivc reads, or breaks the
        format; the message names the dataset and the problem.
    """
    path = Path(path)
    try:
        return _read(path)
    except (SessionError, FileNotFoundError):
        raise
    except (ValueError, TypeError, IndexError, KeyError, AttributeError, UnicodeDecodeError, OSError,
            RuntimeError) as error:
        # a dataset or attribute of the wrong kind that no check above names: still the file's fault
        raise SessionError(f"{path}: malformed session file ({type(error).__name__}: {error})") from None


def _read(path: Path) -> Session:
    with open_ivc_file(path, FORMAT_NAME, FORMAT_VERSION, "session file") as (h5, attrs):
        if attrs.get("length_unit", "m") != "m":
            raise SessionError(
                f"{path}: / attribute length_unit = {attrs['length_unit']!r}: positions must be in metres ('m')"
            )
        session = Session(
            hemisphere=attrs.get("hemisphere", "+x"),
            attrs={k: v for k, v in attrs.items() if k not in _FILE_ATTRS},
        )
        steps = h5.get("steps", {})
        for name in _ordered(steps):
            group = steps[name]
            step_attrs = {key: _decode(value) for key, value in group.attrs.items()}
            valid = _read_dataset(group, "valid")
            session.steps[name] = Step(
                time=_read_dataset(group, "time", required=True),
                signal=_read_dataset(group, "signal"),
                position=_read_dataset(group, "position"),
                quaternion=_read_dataset(group, "quaternion"),
                valid=valid,
                sample_rate_hz=float(step_attrs.get("sample_rate_hz", np.nan)),
                sensor_ids=step_attrs.get("sensor_ids"),
                description=step_attrs.get("description", ""),
                attrs={k: v for k, v in step_attrs.items() if k not in _STEP_ATTRS},
            )
        for name, group in h5.get("truth", {}).items():
            session.truth[name] = Truth(
                position=_read_dataset(group, "position", required=True),
                quaternion=_read_dataset(group, "quaternion", required=True),
            )
    session.validate()
    return session


def _write_step(h5: h5py.File, name: str, step: Step) -> None:
    group = h5.require_group("steps").create_group(name)
    for dataset in _STEP_DATASETS:
        value = getattr(step, dataset)
        if value is not None:
            group.create_dataset(dataset, data=value)
    group.attrs["sample_rate_hz"] = float(step.sample_rate_hz)
    group.attrs["sensor_ids"] = list(step.names)
    group.attrs["description"] = step.description
    for key, value in step.attrs.items():
        group.attrs[key] = value


def _write_truth(h5: h5py.File, name: str, truth: Truth) -> None:
    group = h5.require_group("truth").create_group(name)
    group.create_dataset("position", data=truth.position)
    group.create_dataset("quaternion", data=truth.quaternion)


def _write_header(h5: h5py.File, session: Session) -> None:
    h5.attrs["ivc_format"] = FORMAT_NAME
    h5.attrs["ivc_format_version"] = FORMAT_VERSION
    h5.attrs["length_unit"] = "m"
    h5.attrs["hemisphere"] = session.hemisphere
    for key, value in session.attrs.items():
        h5.attrs[key] = value


def write(session: Session, path: str | os.PathLike, *, overwrite: bool = False,
          on_wait: Callable[[str], None] | None = None,
          corrections: Mapping[str, StepCorrection] | None = None) -> None:
    """Write a whole session atomically; refuse to replace an existing file unless ``overwrite``.

    ``corrections``: {step name: :class:`StepCorrection`}, the flags, residuals and predicted precision of a
    corrected session's steps (``ivc correct``), written into those steps' groups. One writer at a time
    (:func:`writer_lock`; ``on_wait`` is told when this one waits for another).
    """
    path = Path(path)
    with writer_lock(path, on_wait=on_wait):
        _write(session, path, overwrite, corrections)


def _write(session: Session, path: Path, overwrite: bool,
           corrections: Mapping[str, StepCorrection] | None = None) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: exists; add steps to it with add_step, or pass overwrite=True")
    session.validate()
    unknown = sorted(set(corrections or {}) - set(session.steps))
    if unknown:
        raise SessionError(f"corrections of {', '.join(unknown)}: the session has no such step")
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            _write_header(h5, session)
            for name in _ordered(session.steps):
                _write_step(h5, name, session.steps[name])
            for name in _ordered(session.truth):
                _write_truth(h5, name, session.truth[name])
        if corrections:
            with h5py.File(tmp, "a") as h5:
                for name, correction in corrections.items():
                    _write_correction(h5[f"steps/{name}"], correction)


def _write_correction(group: h5py.Group, correction: StepCorrection) -> None:
    group["flags"] = correction.flags
    group["flags"].attrs["meaning"] = FLAGS_MEANING
    group["residual"] = correction.residual
    if correction.precision is not None:
        for key, values, unit in (("precision", correction.precision, "m"),
                                  ("orientation_precision", correction.orientation_precision, "rad")):
            group[key] = values
            group[key].attrs.update(unit=unit, meaning=_PRECISION_MEANING)


def read_corrections(path: str | os.PathLike) -> dict[str, StepCorrection]:
    """{step name: :class:`StepCorrection`} of a corrected session file (``ivc correct``): the steps that carry
    ``flags`` (none for a session that was not corrected). The session itself is :func:`read`."""
    found = {}
    with open_ivc_file(path, FORMAT_NAME, FORMAT_VERSION, "session file") as (h5, _):
        for name, group in h5.get("steps", {}).items():
            if "flags" not in group:
                continue
            residual = _read_dataset(group, "residual", required=True)
            found[name] = StepCorrection(_read_dataset(group, "flags"), residual, _read_dataset(group, "precision"),
                                         _read_dataset(group, "orientation_precision"))
    return found


def _ordered(names) -> list[str]:
    return sorted(names, key=step_order)


def add_step(
    path: str | os.PathLike,
    name: str,
    step: Step,
    truth: Truth | None = None,
    *,
    hemisphere: str = "+x",
    force: bool = False,
    on_wait: Callable[[str], None] | None = None,
) -> None:
    """Add one step (and its truth) to a session file, creating the file if needed.

    Everything already in the file is kept as it is. A step that already exists is
    replaced only with ``force``. The hemisphere of an existing file must match.
    One writer at a time (:func:`writer_lock`): a concurrent writer of the same file
    waits, and ``on_wait`` is told why.
    """
    path = Path(path)
    validate_step(name, step)
    with writer_lock(path, on_wait=on_wait):
        _add_step(path, name, step, truth, hemisphere, force)


def _add_step(path: Path, name: str, step: Step, truth: Truth | None, hemisphere: str, force: bool) -> None:
    if not path.exists():
        session = Session(hemisphere=hemisphere, steps={name: step}, truth={name: truth} if truth else {})
        _write(session, path, overwrite=False)
        return
    existing = read(path)
    if existing.hemisphere != hemisphere:
        raise SessionError(
            f"{path}: / attribute hemisphere = {existing.hemisphere!r} but this step was solved in {hemisphere!r}"
        )
    if name in existing.steps and not force:
        raise FileExistsError(f"{path}: step {name!r} is already recorded; pass force=True to replace it")
    existing.steps[name] = step
    existing.truth.pop(name, None)
    if truth is not None:
        existing.truth[name] = truth
    existing.validate()
    with atomic_path(path, copy_existing=True) as tmp:
        with h5py.File(tmp, "r+") as h5:
            for root in ("steps", "truth"):
                if root in h5 and name in h5[root]:
                    del h5[root][name]
            _write_step(h5, name, step)
            if truth is not None:
                _write_truth(h5, name, truth)
        read(tmp)  # the file about to replace the old one must itself be valid
