"""``ivc serve``: any live source served as an OpenIGTLink server, the way PLUS serves a tracker.

Per frame and per sensor a TRANSFORM named ``<sensor><reference suffix>`` (``cube0ToTracker``, ``Sensor1ToTracker``
for a sensor named by its number alone: PLUS's
``<Tool>To<Reference>`` naming; a name longer than OpenIGTLink's 20 bytes is cut in the header and sent whole in
the ``IGTL_DEVICE_NAME`` metadata), translation in millimetres, time stamped with the frame's time on the
source's clock plus the host's time at start (so stamps are never 0), and PLUS's status metadata:
``TransformStatus`` ``OK`` or ``MISSING`` and ``TransformValid`` ``1`` or ``0`` (a missing sensor's matrix is the
identity). Frames of a rehearsal source carry their step in ``IvcStep``. With ``signals``, each sensor's signal
matrix goes first as an NDARRAY (3, 3) of the same device name and stamp (what ``ivc correct --live`` corrects
best); without, a client receives what a PLUS user gets.

Single-threaded around a selector. Any number of clients; one that leaves does not stop the server. A client that
reads too slowly loses its oldest messages (a tracker cannot wait), unless ``lossless``: then the source is read
only while every client keeps up (a rehearsal or a replay can wait). ``start_on_connect`` holds the source until
the first client connects (a rehearsal then starts when the collector is ready).
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from ivc import rotations
from ivc.collect.stream import LiveSource, Sample, SourceEvent
from ivc.errors import LiveError
from ivc.igtl import DEFAULT_PORT, Downstream, ndarray_content, pack_messages, transform_contents, wrap_metadata

log = logging.getLogger("ivc.serve")
#: a client whose queue grows beyond this many bytes loses its oldest messages (or, lossless, holds the source)
MAX_QUEUE_BYTES = 1 << 22
DEVICE_NAME_BYTES = 20


@dataclass
class ServeStats:
    """Counters of a run: frames read from the source and sent, clients seen, messages a slow client lost."""

    frames: int = 0
    messages: int = 0
    clients: int = 0
    dropped_for_slow_clients: int = 0
    events: int = 0


class IgtlServer:
    """Serve ``source`` (a :class:`~ivc.collect.stream.LiveSource`, not yet opened) on ``(host, port)`` (port 0: a
    free one, see :attr:`address`); see the module docstring. :meth:`run` serves until the source is finished and
    every client has its frames, ``duration`` s have passed, or ``stop`` (a threading.Event) is set."""

    def __init__(self, source: LiveSource, port: int = DEFAULT_PORT, host: str = "127.0.0.1", *,
                 signals: bool = True, reference: str = "Tracker", lossless: bool = False,
                 start_on_connect: bool = False, read_s: float = 0.01):
        self.source = source
        self.signals, self.lossless, self.start_on_connect = signals, lossless, start_on_connect
        self.suffix = f"To{reference}" if reference else ""
        self.read_s = float(read_s)
        self.stats = ServeStats()
        #: added to the source's times to make the stamps (s): the host's whole seconds at start, so no stamp is 0
        self.epoch = float(int(time.time()))
        self._names: dict[tuple[str, ...], list[tuple[str, dict]]] = {}
        self._packed: dict[tuple, tuple[bytes, bytes] | None] = {}
        self._selector = selectors.DefaultSelector()
        self._clients = Downstream(self._selector, log, MAX_QUEUE_BYTES, lossless)
        try:
            self._listener = socket.create_server((host, int(port)))
        except OSError as error:
            raise LiveError(f"cannot serve on {host}:{port} ({error.strerror or error}); choose another port") \
                from None
        self._listener.setblocking(False)
        self._selector.register(self._listener, selectors.EVENT_READ, "listen")
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self.ready = threading.Event()  #: set once the server listens (for a script running it in a thread)

    # ---- encoding -------------------------------------------------------------------------------------------
    def _devices(self, names: tuple[str, ...]) -> list[tuple[str, dict]]:
        """(header device name, constant metadata) per sensor name."""
        devices = self._names.get(names)
        if devices is None:
            devices = []
            for name in names:
                full = f"{'Sensor' if name.isdigit() else ''}{name}{self.suffix}"  # station "1": Sensor1ToTracker
                short = full.encode()[:DEVICE_NAME_BYTES].decode(errors="ignore")
                devices.append((short, {"IGTL_DEVICE_NAME": full} if short != full else {}))
            self._names[names] = devices
        return devices

    @staticmethod
    def transforms(samples: list[Sample]) -> list[tuple[np.ndarray, bytes] | None]:
        """Per sample: (whether each sensor's pose is valid, the TRANSFORM contents of its sensors end to end: a
        missing one's is the identity), computed for all the samples at once; None for a sample without poses."""
        out: list = [None] * len(samples)
        runs: dict[int, list[int]] = {}
        for k, sample in enumerate(samples):
            if sample.position is not None:
                runs.setdefault(sample.n_sensors, []).append(k)
        for n, ks in runs.items():
            position = np.array([samples[k].position for k in ks], float).reshape(-1, 3)
            quaternion = np.array([samples[k].quaternion for k in ks], float).reshape(-1, 4)
            valid = np.array([samples[k].valid for k in ks], bool).reshape(-1)
            ok = valid & np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(quaternion), axis=1)
            m = np.zeros((len(ok), 4, 4))
            m[:] = np.eye(4)
            m[ok, :3, :3] = rotations.to_matrix(quaternion[ok])
            m[ok, :3, 3] = position[ok] * 1e3  # m to mm
            blob = transform_contents(m).tobytes()
            size = 48 * n
            for j, k in enumerate(ks):
                out[k] = (ok[j * n:(j + 1) * n], blob[j * size:(j + 1) * size])
        return out

    def encode(self, sample: Sample, names: tuple[str, ...], transforms: tuple[np.ndarray, bytes] | None = None
               ) -> list[bytes]:
        """The messages of one frame: per sensor an NDARRAY (with ``signals``, when the sample has them) then a
        TRANSFORM (when it has poses) with PLUS's status metadata and, if labelled, ``IvcStep``. ``transforms``:
        the sample's entry of :meth:`transforms`, when computed for many samples at once."""
        n = sample.n_sensors
        names = names[:n] if len(names) >= n else tuple(str(i) for i in range(n))
        devices = self._devices(names)
        stamp = self.epoch + float(sample.time)
        out = []
        if transforms is None and sample.position is not None:
            transforms = self.transforms([sample])[0]
        contents = None
        if transforms is not None:
            ok, contents = transforms
        names = [device for device, _ in devices]
        if self.signals and sample.signal is not None:
            arrays = [ndarray_content(a) for a in sample.signal]
            wraps = [self._metadata(extra, None, sample.step) for _, extra in devices]
            signals = pack_messages("NDARRAY", names, stamp, arrays, wraps)
            if contents is None:
                return signals
        if contents is None:
            return out
        blob = contents
        wraps = [self._metadata(extra, bool(good), sample.step) for (_, extra), good in zip(devices, ok, strict=True)]
        transforms = pack_messages("TRANSFORM", names, stamp, [blob[48 * i:48 * i + 48] for i in range(n)], wraps)
        if not (self.signals and sample.signal is not None):
            return transforms
        for signal, transform in zip(signals, transforms, strict=True):  # each sensor's signal, then its pose
            out += (signal, transform)
        return out

    def _metadata(self, extra: dict, ok: bool | None, step: str | None) -> tuple[bytes, bytes] | None:
        """The packed metadata of a message (cached: a stream repeats a few): long name, PLUS status, step."""
        key = (tuple(extra.items()), ok, step)
        packed = self._packed.get(key)
        if packed is None:
            metadata = dict(extra)
            if ok is not None:
                metadata.update({"TransformStatus": "OK", "TransformValid": "1"} if ok else
                                {"TransformStatus": "MISSING", "TransformValid": "0"})
            if step is not None:
                metadata["IvcStep"] = step
            packed = self._packed[key] = wrap_metadata(metadata) if metadata else None
        return packed

    # ---- the loop -------------------------------------------------------------------------------------------
    def run(self, duration: float | None = None, stop: threading.Event | None = None) -> ServeStats:
        """Serve (see the class docstring); returns the counters. Closes the source and every connection."""
        end = None if duration is None else time.monotonic() + duration
        opened = False
        self.ready.set()
        try:
            while not (stop is not None and stop.is_set()) and (end is None or time.monotonic() < end):
                waiting = self.start_on_connect and not opened and not self._clients.clients
                if not opened and not waiting:
                    self.source.open()
                    opened = True
                finished = opened and getattr(self.source, "finished", False)
                if finished and self._clients.idle:
                    break
                busy = not opened or finished or (self.lossless and self._clients.backlogged)
                for key, mask in self._selector.select(timeout=0.05 if busy else 0):
                    if key.data == "listen":
                        self._clients.accept(self._listener)
                        self.stats.clients = self._clients.accepted
                    else:
                        self._clients.event(key.data, mask)
                if not busy:
                    self._pump()
        finally:
            self.close()
            if opened:
                self.source.close()
        return self.stats

    def _pump(self) -> None:
        """Read the source once and send what it gave."""
        items = self.source.read(self.read_s)
        messages = []
        names = tuple(self.source.sensor_names)
        session = getattr(self.source, "session", None)  # a rehearsal: each step's own sensor names
        samples = [item for item in items if isinstance(item, Sample)]
        transforms = iter(self.transforms(samples))
        for item in items:
            if isinstance(item, SourceEvent):
                self.stats.events += 1
                log.info("source: %s", item.message)
                continue
            step = session.steps.get(item.step) if session is not None and item.step is not None else None
            messages += self.encode(item, tuple(step.names) if step is not None else names, next(transforms))
            self.stats.frames += 1
        if messages:
            self.stats.messages += len(messages)
            self._clients.send(messages)
            self.stats.dropped_for_slow_clients = self._clients.dropped

    def close(self) -> None:
        self._clients.close(self._listener)


def serve(source: LiveSource, port: int = DEFAULT_PORT, host: str = "127.0.0.1", *, duration: float | None = None,
          stop: threading.Event | None = None, **options) -> ServeStats:
    """Serve ``source`` over OpenIGTLink on ``host:port`` until it is finished, ``duration`` s passed or ``stop``
    is set (options: those of :class:`IgtlServer`); returns the counters."""
    return IgtlServer(source, port, host, **options).run(duration, stop)


def serve_source(spec: str, *, seed: int = 0, pause_s: float = 5.0, speed: float = 1.0,
                 frames: dict[str, int | None] | None = None, sensors=None, hemisphere: str = "+x") -> LiveSource:
    """The source ``ivc serve`` streams: ``sim`` or ``sim:SCENE`` (the simulator running the whole protocol in real
    time at ``speed``, ``pause_s`` s of tracker time between steps, frames labelled by step; ``frames`` as
    :meth:`~ivc.sim.Simulator.protocol`'s), ``replay:FILE`` (a session file at its own rate), or a live source of
    the registry (``polhemus:DEVICE``, ``igtl://HOST:PORT``)."""
    from ivc.collect.stream import SessionSource

    if spec == "sim" or spec.startswith("sim:"):
        from ivc.sim import Simulator, load_scene

        scene = load_scene(spec[4:] or "default")
        simulator = Simulator(scene, seed)
        session = simulator.protocol(frames)
        return SessionSource(session, pause_s=pause_s, realtime=True, speed=speed)
    if spec.startswith("replay:"):
        from ivc.session import read

        return SessionSource(read(spec[len("replay:"):]), pause_s=pause_s, realtime=True, speed=speed)
    from ivc.collect.sources import open_live_source

    try:
        return open_live_source(spec, sensors=sensors, hemisphere=hemisphere)
    except ModuleNotFoundError as error:
        raise LiveError(f"source {spec!r} is not available in this installation ({error.name} is missing)") from None
