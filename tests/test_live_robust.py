"""The live link against what real streams carry: phantom headers, large IMAGE messages, unusable poses and
signals, long device names."""

import socket
import threading
import time

import numpy as np
import pyigtl
import pytest
from pyigtl import TransformMessage
from pyigtl.messages import CRC64

from ivc.correct import Corrector
from ivc.live import LiveCorrector, NDArrayMessage
from ivc.live.igtl import BODY_LIMITS, HEADER, Framer
from ivc.live.loop import output_device_name
from tests.helpers import distorted, reported_matrices


def transform(k: int, name: str = "S0") -> bytes:
    m = np.eye(4)
    m[:3, 3] = [300.0 + k, 0.0, 0.0]
    return TransformMessage(m, timestamp=1000.0 + k / 240, device_name=name).pack()


def phantom_header(kind: bytes, size: int) -> bytes:
    """A well-formed header whose body never comes (a sender that crashed mid-message, or noise)."""
    return HEADER.pack(1, kind, b"ghost", 0, 0, size, 0)


def test_a_phantom_tracking_header_is_garbage_at_once():
    framer = Framer()
    framer.feed(phantom_header(b"TRANSFORM", (1 << 20) - 1) + b"".join(transform(k) for k in range(5)))
    frames = framer.messages(now=0.0)
    assert [f.message_type for f in frames] == ["TRANSFORM"] * 5  # nothing waited for the phantom body
    assert framer.garbage == HEADER.size
    assert BODY_LIMITS["TRANSFORM"] < (1 << 20) - 1


def test_a_phantom_header_of_a_large_type_stalls_the_stream_for_the_timeout_only():
    framer = Framer(timeout_s=0.1)
    framer.feed(phantom_header(b"IMAGE", (1 << 20) - 1))
    assert framer.messages(now=0.0) == []
    framer.feed(b"".join(transform(k) for k in range(3)))
    assert framer.messages(now=0.05) == []  # within the timeout: maybe a slow image
    framer.feed(transform(3))
    frames = framer.messages(now=0.2)  # past it: a whole, CRC-valid message follows, so the header was a ghost
    assert [f.device_name for f in frames] == ["S0"] * 4
    assert [round((f.timestamp - 1000.0) * 240) for f in frames] == [0, 1, 2, 3]
    assert framer.garbage == HEADER.size and not framer.buffer
    framer.feed(transform(4))
    assert len(framer.messages(now=0.3)) == 1


def test_a_real_image_is_skipped_by_its_declared_size_without_scanning_it():
    pixels = np.random.default_rng(1).integers(0, 255, (1, 1024, 1280), dtype=np.uint8)
    image = pyigtl.ImageMessage(pixels, device_name="Video").pack()
    assert len(image) > 1 << 20  # over the former 1 MiB cap
    framer = Framer()
    stream = transform(0) + image + transform(1)
    frames = []
    start = time.perf_counter()
    for at in range(0, len(stream), 1 << 16):  # as recv() delivers it
        framer.feed(stream[at:at + (1 << 16)])
        frames += framer.messages()
    seconds = time.perf_counter() - start
    assert [f.message_type for f in frames] == ["TRANSFORM", "IMAGE", "TRANSFORM"]
    assert framer.garbage == 0 and not framer.buffer
    assert seconds < 0.3, seconds  # the former byte-by-byte scan took 0.6 s per image


def test_an_image_with_a_wrong_crc_is_skipped_as_garbage_and_the_stream_resumes():
    image = bytearray(pyigtl.ImageMessage(np.zeros((1, 64, 64), np.uint8), device_name="Video").pack())
    image[-1] ^= 1
    framer = Framer()
    framer.feed(bytes(image) + transform(0))
    assert [f.message_type for f in framer.messages()] == ["TRANSFORM"]
    assert framer.garbage == len(image)


def test_a_header_split_across_reads_is_not_lost_by_the_garbage_scan():
    message = transform(0)
    framer = Framer()
    framer.feed(b"\xff" * 100 + message[:2])
    assert framer.messages() == []
    framer.feed(message[2:])
    assert [f.device_name for f in framer.messages()] == ["S0"]


def test_long_device_names_keep_the_suffix():
    assert output_device_name("S0") == "S0_ivc"
    assert output_device_name("StylusTipToReference") == "StylusTipTo-2523_ivc"  # 20 characters in: tagged
    assert output_device_name("ProbeToTrackerXY") == "ProbeToTrackerXY_ivc"  # 16 + 4 = 20: kept whole
    for n in range(1, 30):
        name = output_device_name("A" * n)
        assert name.endswith("_ivc") and len(name.encode()) <= 20
    assert output_device_name("Sondeé" * 4).endswith("_ivc")  # cut on a character boundary


def test_long_names_that_share_their_start_are_published_under_different_names():
    """Issue 41: `StylusTipToReference` and `StylusTipToReferenc2` were both published as `StylusTipToRefer_ivc`."""
    import hashlib

    first, second = output_device_name("StylusTipToReference"), output_device_name("StylusTipToReferenc2")
    assert first != second and len(first.encode()) == len(second.encode()) == 20
    assert second == output_device_name("StylusTipToReferenc2")  # the same name every run
    assert second.endswith(hashlib.sha1(b"StylusTipToReferenc2").hexdigest()[:4] + "_ivc")
    names = [f"ProbeToTrackerPosition{k}" for k in range(200)]  # 200 names alike in their first 20 bytes
    published: set[str] = set()
    for name in names:
        published.add(output_device_name(name, taken=published))
    assert len(published) == 200 and all(len(p.encode()) <= 20 and p.endswith("_ivc") for p in published)
    assert output_device_name("StylusTipToReference", taken={first}) != first  # a tag already taken grows


def _run_live(table, payloads, names_wanted, caplog, sensors=None):
    """Send ``payloads`` (bytes) to a LiveCorrector; the device names it published, its stats and the log."""
    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(table), listener.getsockname(), ("127.0.0.1", 0), sensors=sensors)
    stop = threading.Event()
    runner = threading.Thread(target=live.run, kwargs={"stop": stop})
    runner.start()
    upstream, _ = listener.accept()
    consumer = socket.create_connection(live.publish_address)
    time.sleep(0.2)  # the client is accepted before the data arrive
    names = []
    try:
        for p in payloads:
            upstream.sendall(p)
        framer = Framer()
        deadline = time.monotonic() + 20
        while len(names) < names_wanted and time.monotonic() < deadline:
            # each wait as long as the whole deadline allows: on a loaded machine the first frame (the pose path's
            # probe map) can take more than a few seconds, which is no failure of the loop
            consumer.settimeout(max(0.1, deadline - time.monotonic()))
            framer.feed(consumer.recv(1 << 16))
            names += [f.device_name for f in framer.messages() if f.message_type == "TRANSFORM"]
    finally:
        stop.set()
        runner.join(10)
        for s in (upstream, consumer, listener):
            s.close()
    return names, live.stats, [r.getMessage() for r in caplog.records]


@pytest.mark.slow
def test_zero_signals_and_absurd_translations_are_dropped_and_logged_and_the_loop_goes_on(exact_table, rng,  # noqa: F811
                                                                                          caplog):
    r, T, S = distorted(rng, 6)
    good = reported_matrices(S).astype(float)
    far = good[0].copy()
    far[:3, 3] = 1e30
    stamp = 2000.0
    payloads = [NDArrayMessage(np.zeros((3, 3)), timestamp=stamp, device_name="Coil").pack(),
                TransformMessage(far, timestamp=stamp, device_name="StylusTipToReference").pack()]
    for k in range(6):
        payloads.append(NDArrayMessage(S[k], timestamp=stamp + (k + 1) / 240, device_name="Coil").pack())
        payloads.append(TransformMessage(good[k], timestamp=stamp + (k + 1) / 240,
                                         device_name="StylusTipToReference").pack())
    names, stats, log = _run_live(exact_table, payloads, 12, caplog)
    assert names.count("Coil_ivc") == 6 and names.count("StylusTipTo-2523_ivc") == 6
    assert stats.rejected == 2 and stats.received == 12
    assert sum("'Coil': dropped a NDARRAY message: the signal matrix is all zeros" in w for w in log) == 1
    assert sum("'StylusTipToReference': dropped a TRANSFORM message: its translation is 1.73e+27 m" in w
               for w in log) == 1
    assert sum("'StylusTipToReference' is published as 'StylusTipTo-2523_ivc'" in w for w in log) == 1


@pytest.mark.slow
def test_two_long_sensor_names_alike_in_their_start_stay_two_streams(exact_table, rng, caplog):  # noqa: F811
    """Issue 41 item 7: both were published as `StylusTipToRefer_ivc`, one stream's poses mixed into the other's."""
    r, T, S = distorted(rng, 4)
    good = reported_matrices(S).astype(float)
    sensors = ("StylusTipToReference", "StylusTipToReferenc2")
    payloads = [TransformMessage(good[k], timestamp=4000.0 + k / 240, device_name=name).pack()
                for k in range(4) for name in sensors]
    names, _, log = _run_live(exact_table, payloads, 8, caplog)
    published = [output_device_name(name) for name in sensors]
    assert published[0] != published[1] and names.count(published[0]) == names.count(published[1]) == 4
    for name, out in zip(sensors, published, strict=True):  # which name stands for which, said once
        assert sum(f"{name!r} is published as {out!r}" in w for w in log) == 1


@pytest.mark.slow
def test_a_phantom_header_does_not_lose_the_messages_after_it(exact_table, rng, caplog):  # noqa: F811
    r, T, S = distorted(rng, 40)
    good = reported_matrices(S).astype(float)
    body = b"\0" * 10
    ghost = HEADER.pack(1, b"VIDEO", b"ghost", 0, 0, (1 << 20) - 1, CRC64(body))
    payloads = [ghost] + [TransformMessage(good[k], timestamp=3000.0 + k / 240, device_name="S0").pack()
                          for k in range(40)]
    names, stats, _ = _run_live(exact_table, payloads, 40, caplog)
    assert names.count("S0_ivc") == 40  # every frame after the ghost published
    assert stats.garbage_bytes >= HEADER.size


def test_a_large_body_is_crc_checked_piecewise_as_it_arrives():
    pixels = np.random.default_rng(2).integers(0, 255, (1, 512, 640), dtype=np.uint8)
    image = bytearray(pyigtl.ImageMessage(pixels, device_name="Video").pack())
    for corrupt in (False, True):
        data = bytearray(image)
        if corrupt:
            data[len(data) // 2] ^= 0x10  # in a part already checked when the end arrives
        framer = Framer()
        stream = bytes(data) + transform(0)
        frames = []
        for at in range(0, len(stream), 50_000):
            framer.feed(stream[at:at + 50_000])
            frames += framer.messages()
        kinds = [f.message_type for f in frames]
        assert kinds == (["TRANSFORM"] if corrupt else ["IMAGE", "TRANSFORM"]), kinds
        assert (framer.garbage > 0) == corrupt


def test_every_kind_of_unusable_message_is_named():
    from ivc.live.igtl import Frame
    from ivc.live.loop import unusable_frames

    good = np.eye(4)
    good[:3, 3] = [300.0, 0, 0]
    scaled, flipped, far, nan = good.copy(), good.copy(), good.copy(), good.copy()
    scaled[:3, :3] *= 2
    flipped[2, 2] = -1
    far[0, 3] = 2e5  # mm: 200 m
    nan[1, 1] = np.nan
    frames = [Frame("TRANSFORM", "a", 0.0, m) for m in (good, scaled, flipped, far, nan)]
    frames += [Frame("NDARRAY", "b", 0.0, np.zeros((3, 3))), Frame("NDARRAY", "b", 0.0, np.eye(3)),
               Frame("STRING", "c", 0.0, None), Frame("TRANSFORM", "d", 0.0, None)]
    problems = unusable_frames(frames, 1e-3)
    assert problems == {1: "its rotation part is not a rotation matrix",
                        2: "its rotation part is not a rotation matrix",
                        3: "its translation is 200 m from the source (more than 100 m)",
                        4: "it holds NaN or inf", 5: "the signal matrix is all zeros (a dropout?)"}


@pytest.mark.slow
def test_every_unusable_signal_matrix_is_dropped_logged_once_and_the_loop_goes_on(exact_table, rng, caplog):  # noqa: F811
    """Zero, huge, denormal (either sign) and non-finite NDARRAY messages (issue 41: one −1e-300 matrix ended the
    loop with ZeroDivisionError): each dropped and counted, one log line per sensor, the good frames corrected."""
    r, T, S = distorted(rng, 6)
    edges = [0.0, 1e300, 1e-300, -1e-300, np.inf, np.nan]
    payloads = []
    for k in range(6):
        stamp = 4000.0 + k / 120
        payloads.append(NDArrayMessage(np.full((3, 3), edges[k]), timestamp=stamp, device_name="Coil").pack())
        payloads.append(NDArrayMessage(S[k], timestamp=stamp + 1 / 240, device_name="Coil").pack())
    names, stats, log = _run_live(exact_table, payloads, 6, caplog)
    assert names.count("Coil_ivc") == 6
    assert stats.rejected == 6 and stats.received == 6 and stats.corrected == 6
    assert sum("'Coil': dropped a NDARRAY message" in w for w in log) == 1
