"""The live loop: one upstream tracking connection in, corrected poses out to every connected client.

Single-threaded around a selector, so nothing waits on anything it does not have to:

* upstream (a client of the tracking server): TRANSFORM messages (sensor pose; translation in
  ``length_unit`` metres per unit, mm by default as PLUS sends), corrected through the pose path
  (:class:`~ivc.correct.reported.PoseCorrector`: the inverse of the tracker's pose-domain
  distortion), or NDARRAY (3, 3) messages (signal matrices) through the signal path, one
  device name per sensor. Lost connections are retried every
  ``retry_s``; each sensor's warm start and predictor restart after a reconnect.
* downstream (a server on ``publish``): per corrected sample a TRANSFORM named
  ``<device><suffix>`` with the input's timestamp and, in its v2 metadata, ``ivc_flags`` (0 =
  trusted; the bits of ``ivc correct``), ``ivc_predicted`` and, where the tracker's noise is known,
  ``ivc_precision_mm`` and ``ivc_orientation_precision_mrad`` (predicted RMS errors); per batch a
  TDATA ``ivc`` with every trusted sensor.
  A client that reads too slowly loses its oldest queued messages, never anyone else's time.

Malformed bytes are skipped up to the next header whose body passes its CRC-64; messages of
other types, unknown sensors (when ``sensors`` is given), out-of-order and repeated
timestamps are dropped. Each kind of problem is logged once (per sensor or client).
"""

from __future__ import annotations

import hashlib
import logging
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np

from ivc import compiled, dipole, rotations
from ivc.correct import INVALID_INPUT, Correction, Corrector
from ivc.correct import kernels as _correct_kernels
from ivc.correct import reported_kernels as _pose_kernels
from ivc.correct.reported import PoseCorrector
from ivc.correct.rigid import agree_with_body, decide_with_body
from ivc.dipole import kernels as _dipole_kernels
from ivc.errors import LiveError, OptionsError
from ivc.fixtures.wand import WandCalibration
from ivc.igtl import Downstream, Framer, TrackingDataMessage, encode_transforms
from ivc.predict import Tuning
from ivc.predict import make as make_predictor
from ivc.table import kernels as _lut_kernels

log = logging.getLogger("ivc.live")
#: a client whose queue grows beyond this many bytes loses its oldest messages
MAX_QUEUE_BYTES = 1 << 20
DEVICE_NAME_BYTES = 20
#: batches whose latency is kept (a live run may last for days)
LATENCY_HISTORY = 1 << 16


#: a TRANSFORM translation beyond this (m) is no tracker's: AC trackers reach a few metres
MAX_RANGE_M = 100.0
#: largest |RᵀR − I| of a TRANSFORM's rotation (float32 matrices are orthonormal to ~1e-6)
MAX_ORTHONORMALITY_ERROR = 1e-2
#: the compiled kernels of the live path (streaming correction of signals and poses, the pose path's seed map)
LIVE_KERNELS = (_correct_kernels.correct_serial, _pose_kernels.invert_serial, _pose_kernels.stream_kernel,
                _pose_kernels.compose_kernel, _lut_kernels.grid_kernel,
                _dipole_kernels.closed_form_pose_kernel, _dipole_kernels.field_kernel, _dipole_kernels.signal_kernel)


def unusable_frames(frames, length_unit: float) -> dict[int, str]:
    """{index in ``frames``: why that decoded TRANSFORM or NDARRAY cannot be corrected}, checked for all the
    frames of a read at once (NaN or inf, a translation beyond MAX_RANGE_M, a rotation part that is not a
    rotation, a signal matrix that cannot be solved: all zeros, denormal or huge)."""
    problems: dict[int, str] = {}
    transforms = [k for k, f in enumerate(frames) if f.message_type == "TRANSFORM" and f.payload is not None]
    if transforms:
        m = np.array([frames[k].payload for k in transforms])
        with np.errstate(all="ignore"):
            finite = np.all(np.isfinite(m.reshape(len(m), 16)), axis=1)
            distance = np.linalg.norm(m[:, :3, 3], axis=1) * length_unit
            R = m[:, :3, :3]
            off = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
            determinant = np.linalg.det(np.where(finite[:, None, None], R, np.eye(3)))
            rotation = (off <= MAX_ORTHONORMALITY_ERROR) & (determinant > 0)
        for n, k in enumerate(transforms):
            if not finite[n]:
                problems[k] = "it holds NaN or inf"
            elif not distance[n] <= MAX_RANGE_M:
                problems[k] = f"its translation is {distance[n]:.3g} m from the source (more than {MAX_RANGE_M:g} m)"
            elif not rotation[n]:
                problems[k] = "its rotation part is not a rotation matrix"
    for k, f in enumerate(frames):
        if f.message_type == "NDARRAY" and f.payload is not None:
            if not np.all(np.isfinite(f.payload)):
                problems[k] = "it holds NaN or inf"
            elif f.payload.shape == (3, 3) and not np.any(f.payload):
                problems[k] = "the signal matrix is all zeros (a dropout?)"
            elif f.payload.shape == (3, 3) and not dipole.usable_signals(f.payload):
                largest = float(np.abs(f.payload).max())
                problems[k] = (f"its signal matrix (largest entry {largest:.3g}) is no source's between "
                               f"{dipole.USABLE_RANGE_M[0]:g} and {dipole.USABLE_RANGE_M[1]:g} m away")
    return problems


@dataclass
class LiveStats:
    """Counters of a run (``rejected``: decoded messages that cannot be corrected: NaN, unusable signals,
    translations beyond MAX_RANGE_M, rotations that are not rotations);
    ``latency_s``: per batch (the latest LATENCY_HISTORY), seconds from its bytes arriving to
    its results being sent."""

    received: int = 0
    corrected: int = 0
    flagged: int = 0
    published_batches: int = 0
    out_of_order: int = 0
    unknown: int = 0
    garbage_bytes: int = 0
    bad_messages: int = 0
    rejected: int = 0
    dropped_for_slow_clients: int = 0
    connections: int = 0
    latency_s: deque = field(default_factory=lambda: deque(maxlen=LATENCY_HISTORY))


class LiveCorrector:
    """Correct (and predict) tracking data streamed over OpenIGTLink; see the module docstring.

    ``source``: (host, port) of the tracking server. ``publish``: (host, port) to serve results
    on (port 0 picks a free one; :attr:`publish_address` tells which). ``predictor``: a filter
    name of ``ivc predict`` with ``horizon`` s and the stream's ``rate_hz``, tuned by ``tuning``
    (:mod:`ivc.predict.tuning`, made at ``rate_hz``) if given.

    Start-up: the compiled kernels of the correction are run once before the publish port opens
    (loaded from numba's cache in a fraction of a second). When they are not in the cache (the
    first run after an install) and ``background_compile`` is on, they compile in a background
    thread instead, and the loop connects at once: until they are ready each frame is corrected by
    the same kernels interpreted (:mod:`ivc.compiled`; same results, a few ms per sensor-frame),
    then by the compiled ones (logged; :attr:`compiled_after_s` says when). A predictor's kernels
    still compile before the port opens.
    """

    def __init__(self, corrector: Corrector, source: tuple[str, int], publish: tuple[str, int] = ("127.0.0.1", 18945),
                 *, length_unit: float = 1e-3, predictor: str | None = None, horizon: float = 0.0,
                 rate_hz: float = 240.0, suffix: str = "_ivc", sensors: list[str] | None = None,
                 retry_s: float = 0.5, tuning: Tuning | None = None, pose_corrector: PoseCorrector | None = None,
                 background_compile: bool = True, rigid_body: WandCalibration | None = None):
        if predictor:
            make_predictor(predictor, rate_hz, tuning)  # an unknown filter or a tuning at another rate: refuse now
        self.corrector, self.source = corrector, source
        self.pose_corrector = pose_corrector or PoseCorrector(corrector.field, corrector.hemisphere)
        self.length_unit, self.suffix = float(length_unit), suffix
        self.predictor, self.horizon, self.rate_hz = predictor, float(horizon), float(rate_hz)
        self.tuning = tuning
        self.sensors = set(sensors) if sensors else None
        if rigid_body is not None and (not sensors or len(sensors) != len(rigid_body.positions)):
            raise OptionsError(f"a rigid body of {len(rigid_body.positions)} sensors needs their device names in its "
                               f"order (sensors=[...], {len(rigid_body.positions)} names), got {sensors or 'none'}")
        #: the rigid body the named sensors are fixed to, in ``sensors``' order (None: none)
        self.rigid_body, self._body_names = rigid_body, list(sensors or ())
        self.retry_s = retry_s
        self.stats = LiveStats()
        self._upstream: socket.socket | None = None
        self._framer = Framer()
        self._next_connect = 0.0
        self._last_time: dict[str, float] = {}
        self._streams: dict = {}
        self._stream_time: dict[str, float] = {}  # each predictor stream's latest time stamp (s)
        self._logged: set = set()
        self._published: dict[str, str] = {}  # sensor name -> the device name its corrections are published under
        #: seconds from start-up until the background compilation finished (None: none ran, or not yet)
        self.compiled_after_s: float | None = None
        self._compiler: threading.Thread | None = None
        if background_compile and compiled.SMALL > 0 and not all(compiled.is_ready(k) for k in LIVE_KERNELS):
            self._compiler = threading.Thread(target=self._compile, args=(time.perf_counter(),), daemon=True,
                                              name="ivc-compile")
            log.info("compiling the correction kernels in the background (first run after an install); frames are "
                     "corrected by their interpreted forms until they are ready")
            self._compiler.start()
        else:
            self._warm_up(self.corrector, self.pose_corrector)  # compiled (or loaded) before anyone connects
        if self.predictor:
            self._predicted("warm-up", np.array([1.0, 0.0, 0.0, 0.0]), True)
            self._streams.clear()
            self._stream_time.clear()
        self._selector = selectors.DefaultSelector()
        self._clients = Downstream(self._selector, log, MAX_QUEUE_BYTES)
        self._listener = socket.create_server(publish, reuse_port=False)
        self._listener.setblocking(False)
        self._selector.register(self._listener, selectors.EVENT_READ, "listen")
        self.publish_address = self._listener.getsockname()[:2]

    @property
    def compiling(self) -> bool:
        """Whether the background compilation (see the class docstring) is still running."""
        return self._compiler is not None and self._compiler.is_alive()

    @staticmethod
    def _warm_up(corrector: Corrector, pose_corrector: PoseCorrector) -> None:
        """Run every compiled step of the correction once, so the first frames do not wait for it."""
        centre = corrector.field.grid.origin + 0.5 * corrector.field.grid.spacing * (
            np.array(corrector.field.grid.shape) - 1)
        with compiled.compiling():
            corrector.update(dipole.signal(centre[None], np.eye(3)[None]), sensors=["warm-up"])
            corrector.reset()
            pose_corrector.warm_up(centre)

    def _compile(self, start: float) -> None:
        """The background compilation: the same warm-up on copies of the correctors (their stream state is
        the loop's)."""
        try:
            self._warm_up(Corrector(self.corrector.field, self.corrector.hemisphere),
                          PoseCorrector(self.pose_corrector.field, self.pose_corrector.hemisphere,
                                        solver=self.pose_corrector.solver))
        except Exception as error:  # noqa: BLE001 - the interpreted forms keep correcting; say why
            log.error("background compilation failed (%s); correcting with the interpreted kernels", error)
            return
        self.compiled_after_s = time.perf_counter() - start
        log.info("compiled kernels ready after %.1f s: correcting with them from now on", self.compiled_after_s)

    # ---- logging once -------------------------------------------------------------------------
    def _once(self, key, message: str, level: int = logging.WARNING) -> None:
        if key not in self._logged:
            self._logged.add(key)
            log.log(level, message)

    # ---- upstream -----------------------------------------------------------------------------
    def _connect(self) -> None:
        try:
            sock = socket.create_connection(self.source, timeout=0.2)
        except OSError as error:
            self._once(("down", self.stats.connections), f"tracking server {self.source[0]}:{self.source[1]} "
                       f"unreachable ({error.strerror or error}); retrying every {self.retry_s} s")
            self._next_connect = time.monotonic() + self.retry_s
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._upstream = sock
        self._framer.clear()  # a partial message from the last connection is not continued by this one
        self._selector.register(sock, selectors.EVENT_READ, "upstream")
        self.stats.connections += 1
        self.corrector.reset()
        self.pose_corrector.reset()  # a gap: no sensor continues its track
        self._streams.clear()
        self._stream_time.clear()
        self._last_time.clear()
        log.info("connected to tracking server %s:%d", *self.source)

    def _disconnect(self, reason: str) -> None:
        if self._upstream is not None:
            self._selector.unregister(self._upstream)
            self._upstream.close()
            self._upstream = None
            log.warning("tracking server %s:%d: %s; reconnecting", self.source[0], self.source[1], reason)
        self._next_connect = time.monotonic() + self.retry_s

    def _read_upstream(self) -> None:
        try:
            data = self._upstream.recv(1 << 20)  # a video frame arrives in a few reads
        except (BlockingIOError, InterruptedError):
            return
        except OSError as error:
            self._disconnect(f"connection lost ({error.strerror or error})")
            return
        if not data:
            self._disconnect("connection closed")
            return
        self._framer.feed(data)
        self._drain(time.perf_counter())

    def _drain(self, arrived: float) -> None:
        """Process the whole messages the framer holds (also while a header waits for its body: its timeout)."""
        frames = self._framer.messages()
        if self._framer.garbage > self.stats.garbage_bytes:  # the framer counts over the whole run
            self._once(("garbage", self.stats.connections), "skipped malformed bytes from the tracking server "
                       "(no valid OpenIGTLink header or CRC); resynchronised on the next valid message")
            self.stats.garbage_bytes = self._framer.garbage
        if self._framer.bad > self.stats.bad_messages:
            self._once("bad", "dropped a message whose body could not be unpacked")
            self.stats.bad_messages = self._framer.bad
        if frames:
            self._process(frames, arrived)

    # ---- correction ---------------------------------------------------------------------------
    def _samples(self, frames) -> list[tuple[str, float, np.ndarray | None, tuple | None]]:
        """(device, timestamp, signal matrix (3, 3) or None, reported pose (position m, rotation) or None) of the
        usable tracking messages, in arrival order: NDARRAY messages carry signals, TRANSFORM messages poses."""
        names, times, signals, poses = [], [], [], []
        problems = unusable_frames(frames, self.length_unit)
        for k, f in enumerate(frames):
            if f.message_type not in ("TRANSFORM", "NDARRAY"):
                self._once(("type", f.message_type), f"ignoring {f.message_type} messages (expected TRANSFORM poses "
                           "or NDARRAY 3x3 signal matrices)", logging.INFO)
                continue
            name = f.device_name
            if self.sensors is not None and name not in self.sensors:
                self.stats.unknown += 1
                self._once(("unknown", name), f"ignoring unknown sensor {name!r} (not among the sensors asked for)")
                continue
            if f.payload is None:
                continue  # undecodable: counted by the framer
            last = self._last_time.get(name)
            if last is not None and f.timestamp != 0.0 and f.timestamp <= last:
                self.stats.out_of_order += 1
                self._once(("order", name), f"sensor {name!r}: dropped a message older than (or as old as) the last "
                           "one; this and later ones are counted, not logged")
                continue
            problem = problems.get(k)
            if problem:
                self.stats.rejected += 1
                self._once(("rejected", name), f"sensor {name!r}: dropped a {f.message_type} message: {problem}; "
                           "later ones are counted, not logged")
                continue
            self._last_time[name] = f.timestamp
            if f.message_type == "TRANSFORM":
                # float32 matrices are not quite orthonormal: take the nearest rotation
                rotation = rotations.to_matrix(rotations.from_matrix(np.asarray(f.payload[:3, :3], float)))
                poses.append((np.asarray(f.payload[:3, 3], float) * self.length_unit, rotation))
                signals.append(None)
            else:
                a = f.payload
                if a.shape != (3, 3):
                    self._once(("shape", name), f"sensor {name!r}: NDARRAY of shape {a.shape} is not a 3x3 signal "
                               "matrix; dropped")
                    continue
                signals.append(a)
                poses.append(None)
            names.append(name)
            times.append(f.timestamp)
        return list(zip(names, times, signals, poses, strict=True))

    def _process(self, frames, arrived: float) -> None:
        samples = self._samples(frames)
        self.stats.received += len(samples)
        while samples:  # rounds in which each sensor appears once, in arrival order
            seen, now, later = set(), [], []
            for s in samples:
                (later if s[0] in seen else now).append(s)
                seen.add(s[0])
            self._correct_round(now)
            samples = later
        self.stats.latency_s.append(time.perf_counter() - arrived)

    def _predicted(self, name: str, quaternion: np.ndarray, ok: bool, stamp: float = 0.0) -> np.ndarray | None:
        """The sample predicted ``horizon`` s ahead; the predictor runs on the messages' time stamps (s): one without
        a stamp (0), or not after the last, counts one nominal period later; a sensor that never stamps, none."""
        stream = self._streams.get(name)
        if stream is None:
            stream = self._streams[name] = make_predictor(self.predictor, self.rate_hz, self.tuning,
                                                          self.horizon).stream(1)
        before = self._stream_time.get(name)
        if stamp > 0.0 and (before is None or stamp > before):
            self._stream_time[name] = when = float(stamp)
        elif before is None:
            when = None
        else:
            self._stream_time[name] = when = before + 1.0 / self.rate_hz
        stream.update(np.where(ok, quaternion, np.nan)[None], np.array([ok]), time=when)
        q = stream.predict(self.horizon)[0]
        return q if np.all(np.isfinite(q)) else None

    def _correct(self, samples, names) -> Correction:
        """Signals through the signal path, reported poses through the pose path, in the samples' order."""
        by_pose = np.array([s[3] is not None for s in samples])
        if not by_pose.any():
            return self.corrector.update(np.array([s[2] for s in samples]), sensors=names)
        if by_pose.all():
            return self.pose_corrector.update(np.array([s[3][0] for s in samples]),
                                              np.array([s[3][1] for s in samples]), sensors=names)
        parts = {}
        for flag in (False, True):
            idx = np.flatnonzero(by_pose == flag)
            parts[flag] = (idx, self._correct([samples[i] for i in idx], [names[i] for i in idx]))
        n = len(samples)
        merged = Correction(np.empty((n, 3)), np.empty((n, 4)), np.empty(n, np.uint8), np.empty(n),
                            np.empty(n, np.int64), np.full(n, np.nan), np.full(n, np.nan))
        for idx, out in parts.values():
            for key in ("position", "quaternion", "flags", "residual", "iterations", "precision",
                        "orientation_precision"):
                if getattr(out, key) is not None:
                    getattr(merged, key)[idx] = getattr(out, key)
        return merged

    def _agree(self, out: Correction, names: list[str], samples) -> None:
        """Flag (4), in place, the trusted sensors of a round that their rigid body's other trusted sensors of the
        round disagree with (:func:`ivc.correct.rigid.agree_with_body`); a sensor missing from the round counts as
        untrusted. Then trust the reported poses the map produces twice where the body puts them on one branch
        (:func:`ivc.correct.rigid.decide_with_body`; not a signal's sample: it has no reported pose, its signal
        decides)."""
        W = len(self._body_names)
        at = {name: n for n, name in enumerate(names)}
        rows = np.array([at.get(name, -1) for name in self._body_names])
        present = rows >= 0
        got = rows[present]
        # the round as one frame of the body (a missing sensor: no pose, INVALID_INPUT), and its reported poses
        body = Correction(np.full((1, W, 3), np.nan), np.full((1, W, 4), np.nan),
                          np.full((1, W), INVALID_INPUT, np.uint8), np.full((1, W), np.nan), np.zeros((1, W), np.int64),
                          *(None if out.precision is None else np.full((1, W), np.nan) for _ in range(2)))
        fields = ("position", "quaternion", "flags", "residual", "iterations") + (
            () if out.precision is None else ("precision", "orientation_precision"))
        for name in fields:
            getattr(body, name)[0, present] = getattr(out, name)[got]
        flagged = agree_with_body(body, self.rigid_body)[0]
        out.flags[got] = body.flags[0, present]
        # a sensor found on the wrong branch does not continue its track: its next pose gets the full test
        self.pose_corrector.reset([name for name, f in zip(self._body_names, flagged, strict=True) if f])
        reported = np.array([present[n] and samples[rows[n]][3] is not None for n in range(W)])
        if not reported.any():
            return
        position, quaternion = np.full((1, W, 3), np.nan), np.full((1, W, 4), np.nan)
        position[0, reported] = [samples[rows[n]][3][0] for n in np.flatnonzero(reported)]
        quaternion[0, reported] = rotations.from_matrix(
            np.array([samples[rows[n]][3][1] for n in np.flatnonzero(reported)], dtype=float))
        decided = decide_with_body(self.pose_corrector, position, quaternion, body, self.rigid_body)[0]
        for name in fields:
            getattr(out, name)[rows[decided]] = getattr(body, name)[0, decided]

    def _correct_round(self, samples) -> None:
        names = [s[0] for s in samples]
        stamps = [s[1] for s in samples]
        out = self._correct(samples, names)
        if self.rigid_body is not None:
            self._agree(out, names, samples)
        ok = out.flags == 0
        self.stats.corrected += int(ok.sum())
        self.stats.flagged += int((~ok).sum())
        sent = np.all(np.isfinite(out.position), axis=1)  # invalid input: nothing to send
        quaternion = out.quaternion.copy()
        predicted = np.zeros(len(samples), bool)
        if self.predictor:
            for n, name in enumerate(names):
                if sent[n]:
                    q = self._predicted(name, quaternion[n], bool(ok[n]), stamps[n])
                    if q is not None:
                        quaternion[n], predicted[n] = q, True
        m = np.zeros((len(samples), 4, 4))
        m[:, :3, :3] = rotations.to_matrix(np.where(sent[:, None], quaternion, [1.0, 0.0, 0.0, 0.0]))
        m[:, :3, 3] = out.position / self.length_unit
        m[:, 3, 3] = 1.0
        index = np.flatnonzero(sent)
        metadata = [{"ivc_flags": str(int(out.flags[n])), "ivc_predicted": "1" if predicted[n] else "0"}
                    for n in index]
        if out.precision is not None:  # the predicted precision, where the tracker's noise is known
            for meta, n in zip(metadata, index, strict=True):
                if np.isfinite(out.precision[n]):
                    meta["ivc_precision_mm"] = f"{1000 * out.precision[n]:.4g}"
                    meta["ivc_orientation_precision_mrad"] = f"{1000 * out.orientation_precision[n]:.4g}"
        messages = encode_transforms([self._published_name(names[n]) for n in index], [stamps[n] for n in index],
                                     m[index], metadata)
        tools = {names[n]: m[n] for n in np.flatnonzero(ok & sent)}
        if tools:
            messages.append(TrackingDataMessage(tools, timestamp=stamps[-1], device_name="ivc").pack())
        self._send_all(messages)
        self.stats.published_batches += 1

    def _published_name(self, name: str) -> str:
        """``<name><suffix>`` within OpenIGTLink's 20 bytes (:func:`output_device_name`): a long name loses the end
        of its base, never the suffix (else it would collide with the raw stream's node), and gains a tag that keeps
        it apart from every other sensor's; said once per name, with the name it stands for."""
        published = self._published.get(name)
        if published is None:
            published = self._published[name] = output_device_name(name, self.suffix, set(self._published.values()))
            if published != name + self.suffix:
                self._once(("renamed", name), f"sensor {name!r} is published as {published!r}: OpenIGTLink device "
                           f"names hold {DEVICE_NAME_BYTES} bytes, so its name was shortened to keep {self.suffix!r} "
                           "and tagged from the whole name to tell it from other sensors")
        return published

    # ---- downstream ---------------------------------------------------------------------------
    def _send_all(self, messages: list[bytes]) -> None:
        self._clients.send(messages)
        self.stats.dropped_for_slow_clients = self._clients.dropped

    # ---- the loop -----------------------------------------------------------------------------
    def run(self, duration: float | None = None, stop=None) -> LiveStats:
        """Serve until ``duration`` s have passed or ``stop`` (a threading.Event) is set; returns the stats."""
        end = None if duration is None else time.monotonic() + duration
        try:
            while not (stop is not None and stop.is_set()) and (end is None or time.monotonic() < end):
                if self._upstream is None and time.monotonic() >= self._next_connect:
                    self._connect()
                for key, mask in self._selector.select(timeout=0.05):
                    if key.data == "listen":
                        self._clients.accept(self._listener)
                    elif key.data == "upstream":
                        if self._upstream is not None:
                            self._read_upstream()
                    else:
                        self._clients.event(key.data, mask)
                if self._upstream is not None and self._framer.waiting:
                    self._drain(time.perf_counter())
        finally:
            self.close()
        return self.stats

    def close(self) -> None:
        if self.compiling:
            log.info("waiting for the background compilation to finish (it is cached for the next run)")
            self._compiler.join()
        if self._upstream is not None:
            self._selector.unregister(self._upstream)
            self._upstream.close()
            self._upstream = None
        self._clients.close(self._listener)


def output_device_name(name: str, suffix: str = "_ivc", taken: Collection[str] = ()) -> str:
    """The device name ``name`` is published under, within OpenIGTLink's DEVICE_NAME_BYTES bytes of UTF-8.

    ``name + suffix`` when it fits. A longer name keeps the suffix whole and the start of its base (cut on a
    character boundary), then ``-`` and a tag of hex digits of the whole name's SHA-1, so two names that share
    their first bytes (``StylusTipToReference``, ``StylusTipToReferenc2``) are published under two names, the same
    ones every run. ``taken``: names already published for other sensors; the tag grows until the name is not
    among them."""
    whole = name + suffix
    if len(whole.encode()) <= DEVICE_NAME_BYTES and whole not in taken:
        return whole
    digest = hashlib.sha1(name.encode()).hexdigest()
    for digits in range(4, len(digest) + 1):
        tail = f"-{digest[:digits]}{suffix}"
        room = max(DEVICE_NAME_BYTES - len(tail.encode()), 0)
        published = (name.encode()[:room].decode(errors="ignore") + tail).encode()[:DEVICE_NAME_BYTES].decode(
            errors="ignore")
        if published not in taken:
            return published
    raise LiveError(f"no unique OpenIGTLink device name left for sensor {name!r}")
