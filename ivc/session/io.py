"""Read and write session files (docs/session-format.md).

Every write is atomic: the new file is written beside the target under a temporary
name and renamed over it only once complete and valid, so an interrupted write
leaves the previous file as it was. A step that is already in a file is never
replaced unless the caller passes ``force=True``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
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


def write(session: Session, path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Write a whole session atomically; refuse to replace an existing file unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: exists; add steps to it with add_step, or pass overwrite=True (--force)")
    session.validate()
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        _write_header(h5, session)
        for name in _ordered(session.steps):
            _write_step(h5, name, session.steps[name])
        for name in _ordered(session.truth):
            _write_truth(h5, name, session.truth[name])


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
) -> None:
    """Add one step (and its truth) to a session file, creating the file if needed.

    Everything already in the file is kept as it is. A step that already exists is
    replaced only with ``force``. The hemisphere of an existing file must match.
    """
    path = Path(path)
    validate_step(name, step)
    if not path.exists():
        session = Session(hemisphere=hemisphere, steps={name: step}, truth={name: truth} if truth else {})
        write(session, path)
        return
    existing = read(path)
    if existing.hemisphere != hemisphere:
        raise SessionError(
            f"{path}: / attribute hemisphere = {existing.hemisphere!r} but this step was solved in {hemisphere!r}"
        )
    if name in existing.steps and not force:
        raise FileExistsError(f"{path}: step {name!r} is already recorded; pass --force to replace it")
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
