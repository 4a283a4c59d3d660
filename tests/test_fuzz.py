"""Fuzzing every reader: any bytes (or any content in a well-formed container) give a valid result or a clean
ivc error, never another exception, and the input file is never changed. 2,000 examples per reader."""

import json
import os
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pyigtl import StringMessage, TransformMessage

from ivc.collect import read_csv, read_plus, write_csv
from ivc.errors import IvcError
from ivc.live import NDArrayMessage
from ivc.live.igtl import HEADER_SIZE, Framer
from ivc.lut import read as read_lut
from ivc.session import Step
from ivc.session import read as read_session
from ivc.session.model import STEPS

#: slow (2,000 generated inputs per reader, about two minutes); deselected by -m "not slow"
pytestmark = pytest.mark.slow

EXAMPLES = int(os.environ.get("IVC_FUZZ_EXAMPLES", 2000))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def scratch():
    with tempfile.TemporaryDirectory(prefix="ivc-fuzz-") as folder:
        yield Path(folder)


def _valid_csv() -> bytes:
    frames, sensors = 4, 2
    rng = np.random.default_rng(3)
    q = rng.standard_normal((frames, sensors, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    step = Step(np.arange(frames) / 240.0, rng.standard_normal((frames, sensors, 3, 3)),
                0.3 + 0.01 * rng.standard_normal((frames, sensors, 3)), q, sensor_ids=["a", "b"])
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "seed.csv"
        write_csv(step, path)
        return path.read_bytes()


SEED_CSV = _valid_csv()
SEED_PLUS = b"""ObjectType = Image
NDims = 3
DimSize = 0 0 2
Seq_Frame0000_ToolToTrackerTransform = 1 0 0 100 0 1 0 0 0 0 1 0 0 0 0 1
Seq_Frame0000_ToolToTrackerTransformStatus = OK
Seq_Frame0000_Timestamp = 1.0
Seq_Frame0001_ToolToTrackerTransform = 0 -1 0 100 1 0 0 0 0 0 1 0 0 0 0 1
Seq_Frame0001_ToolToTrackerTransformStatus = MISSING
Seq_Frame0001_Timestamp = 1.5
ElementType = MET_UCHAR
ElementDataFile = LOCAL
"""


_ANY_BYTES = st.binary(max_size=400)
_ONE_IN_TEN = st.integers(0, 9)
_EDITS = st.integers(1, 6)
_AT = st.integers(0, 1 << 16)
_OPS = st.sampled_from(["replace", "insert", "delete", "cut", "token"])
_BYTE = st.integers(0, 255)
_INSERT = st.binary(min_size=1, max_size=8)
_SPAN = st.integers(1, 20)
_TOKENS = st.sampled_from([b",", b"\n", b"nan", b"1e30", b"-", b"0", b"\xef\xbb\xbf", b"=", b"inf", b" ",
                           b"Seq_Frame0009_", b"Transform", b"\r\n"])


@st.composite
def mutated(draw, seed: bytes):
    """``seed`` with a few bytes replaced, inserted or deleted, or cut short; or any bytes at all."""
    if draw(_ONE_IN_TEN) == 0:
        return draw(_ANY_BYTES)
    data = bytearray(seed)
    for _ in range(draw(_EDITS)):
        at = draw(_AT) % max(len(data), 1)
        op = draw(_OPS)
        if op == "replace" and data:
            data[at] = draw(_BYTE)
        elif op == "insert":
            data[at:at] = draw(_INSERT)
        elif op == "delete":
            del data[at:at + draw(_SPAN)]
        elif op == "cut":
            del data[at:]
        else:  # a plausible but wrong token
            data[at:at] = draw(_TOKENS)
    return bytes(data)


_CSV_INPUTS = mutated(SEED_CSV)
_PLUS_INPUTS = mutated(SEED_PLUS)


def _read_clean(path: Path, data: bytes, reader) -> None:
    path.write_bytes(data)
    try:
        reader(path)
    except IvcError:
        pass
    assert path.read_bytes() == data  # the input is never changed


@FUZZ
@given(data=_CSV_INPUTS)
def test_fuzz_recording_csv(scratch, data):
    _read_clean(scratch / "rec.csv", data, read_csv)


@FUZZ
@given(data=_PLUS_INPUTS)
def test_fuzz_plus_sequence(scratch, data):
    _read_clean(scratch / "seq.igs.mha", data, read_plus)


_DTYPES = st.sampled_from([np.float64, np.float32, np.int32, np.uint8, np.bool_, "S4", np.complex64])
# strategies are built once here: building them inside a draw costs more than the read under test
_ANY_SHAPE = hnp.array_shapes(min_dims=0, max_dims=4, max_side=9)
_KINDS = st.sampled_from(["normal", "unit", "special"])
_SEEDS = st.integers(0, 2**32 - 1)
_LIKELY = st.integers(0, 3)  # 0: any shape; else the shape the format asks for
_SPECIAL = np.array([np.nan, np.inf, 0.0, 1e30, -1.0])


@st.composite
def arrays(draw, likely: tuple):
    """An array of any listed dtype, of shape ``likely`` (3 times in 4) or any small shape: random normal
    numbers, unit vectors along the last axis, or numbers sprinkled with NaN, inf, 0, 1e30 and -1."""
    dtype = np.dtype(draw(_DTYPES))
    shape = likely if draw(_LIKELY) else draw(_ANY_SHAPE)
    rng = np.random.default_rng(draw(_SEEDS))
    a = rng.standard_normal(shape)
    kind = draw(_KINDS)
    if kind == "unit" and a.ndim:
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
    elif kind == "special":
        a = np.where(rng.random(shape) < 0.3, rng.choice(_SPECIAL, shape), a)
    with np.errstate(all="ignore"):
        return a.astype(str).astype(dtype) if dtype.kind == "S" else a.astype(dtype)


# HDF5 strings hold no NUL and no lone surrogate
_TEXT = st.text(st.characters(blacklist_characters="\0", blacklist_categories=("Cs",)), max_size=8)
_ATTRIBUTES = st.one_of(st.integers(-3, 300), st.floats(allow_nan=True), _TEXT,
                        st.lists(st.integers(-2, 12), max_size=4).map(np.array),
                        st.binary(max_size=4).filter(lambda b: b"\0" not in b))
_SESSION_KIND = st.sampled_from(["session", "session", "lut", "x"])
_VERSION = st.sampled_from([1, 1, 1, 2, "1"])
_HEMISPHERE = st.sampled_from(["+x", "-z", "sideways"])
_FRAMES = st.integers(1, 6)
_SENSORS = st.sampled_from([1, 2, 8])
_STEP_NAMES = st.lists(st.sampled_from([*STEPS, "other"]), max_size=3, unique=True)
_STEP_ATTRS = st.lists(st.sampled_from(["sample_rate_hz", "sensor_ids", "description", "declared_position",
                                        "declared_quaternion"]), unique=True)
_COIN = st.booleans()


@st.composite
def session_files(draw):
    """Well-formed HDF5 with random session content: steps, datasets of any shape and type, attributes."""
    root = {"ivc_format": draw(_SESSION_KIND), "ivc_format_version": draw(_VERSION),
            "hemisphere": draw(_HEMISPHERE)}
    F, N = draw(_FRAMES), draw(_SENSORS)
    steps = {}
    for name in draw(_STEP_NAMES):
        datasets = {"time": draw(arrays((F,)))}
        for key, shape in (("signal", (F, N, 3, 3)), ("position", (F, N, 3)), ("quaternion", (F, N, 4)),
                           ("valid", (F, N))):
            if draw(_COIN):
                datasets[key] = draw(arrays(shape))
        attrs = {k: draw(_ATTRIBUTES) for k in draw(_STEP_ATTRS)}
        steps[name] = (datasets, attrs)
    return root, steps


def _write_h5(path: Path, root: dict, groups: dict) -> None:
    with h5py.File(path, "w") as h5:
        for k, v in root.items():
            h5.attrs[k] = v
        for name, (datasets, attrs) in groups.items():
            group = h5.require_group(name)
            for k, v in datasets.items():
                group[k] = v
            for k, v in attrs.items():
                group.attrs[k] = v


_JUNK = st.binary(max_size=64)
_AS_BYTES = st.integers(0, 19)


@FUZZ
@given(content=session_files(), junk=_JUNK, as_bytes=_AS_BYTES)
def test_fuzz_session_file(scratch, content, junk, as_bytes):
    path = scratch / "s.h5"
    if as_bytes == 0:
        _read_clean(path, junk, read_session)
        return
    root, steps = content
    _write_h5(path, root, {f"steps/{name}": value for name, value in steps.items()})
    _read_clean(path, path.read_bytes(), read_session)


_GRID_SHAPE = st.one_of(st.just((3, 3, 2)), st.lists(st.integers(-1, 4), min_size=0, max_size=4).map(tuple))
_LUT_KIND = st.sampled_from(["lut", "lut", "session"])
_LUT_VERSION = st.sampled_from([1, 1, 1, 7])
_LUT_HEMISPHERE = st.sampled_from(["+x", "+y", "up"])
_SPACING = st.one_of(st.just(0.05), st.floats(allow_nan=True), _TEXT)
_PRESENT = st.integers(0, 7)
_JSON = st.one_of(st.just("{}"), _TEXT.map(json.dumps), _TEXT)


@st.composite
def table_files(draw):
    """Well-formed HDF5 with random table content."""
    shape = draw(_GRID_SHAPE)
    root = {"ivc_format": draw(_LUT_KIND), "ivc_format_version": draw(_LUT_VERSION),
            "hemisphere": draw(_LUT_HEMISPHERE)}
    grid = {"origin": np.zeros(3) if draw(_COIN) else draw(arrays((3,))), "spacing": draw(_SPACING),
            "shape": np.array(shape, dtype=np.int64)}
    datasets = {}
    for key, tail in (("values", (3, 3)), ("valid", ()), ("support", ())):
        if draw(_PRESENT):
            datasets[key] = draw(arrays((3, 3, 2, *tail)))
    texts = {k: draw(_JSON) for k in ("fit", "provenance")}
    return root, grid, datasets, texts


@FUZZ
@given(content=table_files(), junk=_JUNK, as_bytes=_AS_BYTES)
def test_fuzz_table_file(scratch, content, junk, as_bytes):
    path = scratch / "t.h5"
    if as_bytes == 0:
        _read_clean(path, junk, read_lut)
        return
    root, grid, datasets, texts = content
    with h5py.File(path, "w") as h5:
        for k, v in root.items():
            h5.attrs[k] = v
        g = h5.create_group("grid")
        for k, v in grid.items():
            g.attrs[k] = v
        for k, v in datasets.items():
            h5[k] = v
        for k, v in texts.items():
            h5.create_group(k).attrs["json"] = v
    _read_clean(path, path.read_bytes(), read_lut)


_MESSAGES = [TransformMessage(np.eye(4), timestamp=5.0, device_name="S0").pack(),
             NDArrayMessage(np.arange(9.0).reshape(3, 3), timestamp=6.0, device_name="S1").pack(),
             StringMessage("hello", device_name="S2").pack(),
             NDArrayMessage(np.zeros((2, 2, 2)), device_name="S3").pack()]


_PARTS = st.lists(st.one_of(st.sampled_from(_MESSAGES), mutated(_MESSAGES[0]), st.binary(max_size=80)), max_size=8)
_CUTS = st.lists(st.integers(1, 200), max_size=10)
_CLOCK = st.lists(st.floats(0, 1), max_size=10)


@FUZZ
@given(parts=_PARTS, cuts=_CUTS, clock=_CLOCK)
def test_fuzz_openigtlink_framer(parts, cuts, clock):
    stream = b"".join(parts)
    framer = Framer(timeout_s=0.1)
    frames, at, now = [], 0, 0.0
    for k, cut in enumerate([*cuts, len(stream)]):
        framer.feed(stream[at:at + cut])
        at += cut
        now += clock[k] if k < len(clock) else 0.2
        frames += framer.messages(now=now)
        if at >= len(stream):
            break
    frames += framer.messages(now=now + 1.0)
    for f in frames:
        assert isinstance(f.message_type, str) and isinstance(f.device_name, str)
        assert f.payload is None or isinstance(f.payload, np.ndarray)
    whole = [m for m in parts if m in _MESSAGES]
    if len(whole) == len(parts):  # nothing but valid messages: every one comes out, in order, with no garbage
        assert len(frames) == len(whole) and framer.garbage == 0
    assert len(framer.buffer) < HEADER_SIZE + max(len(stream), 1)
