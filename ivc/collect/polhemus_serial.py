"""A Polhemus Liberty or Patriot on a serial port, configured by ivc and read as a live source (``polhemus:DEVICE``).

ivc sets the tracker up itself (docs/polhemus.md names the public document behind each command): binary output
(``F1``), centimetres (``U1``), the session's hemisphere on every station (``H*,x,y,z``), an output list of position,
quaternion and frame count on every station (``O*,2,7,9``), then continuous output (``C``); ``P`` stops it. Each
binary record is an 8-byte header (preamble ``LY`` for a Liberty, ``PA`` for a Patriot, station number, initiating
command, error code, a reserved byte, payload size as a little-endian int16) and a 32-byte payload of little-endian
float32 x, y, z (cm), float32 quaternion w, x, y, z and uint32 frame count. The records of many frames are decoded at
once (a numpy structured dtype over the byte buffer), not one by one.

What the source reports (``Sample``, one per tracker frame, stations in the step's order):

* time = frame count / the tracker's rate (Liberty 240 Hz, Patriot 60 Hz), never the host clock; when the frame count
  restarts (the tracker was reset or power-cycled), the time line continues from the last frame;
* a station whose position is exactly (0, 0, 0) (a dropout), whose record carries an error code, whose quaternion is
  not unit, or whose record is missing from its frame is ``valid = False`` (pose NaN);
* a frame sent twice (same frame count) is kept once; garbage between records is skipped by resynchronising on the
  next header and reported; a tracker that falls silent (reset mid-stream) is configured again and that is reported;
  a port that vanishes is reopened a bounded number of times, then ``LiveError`` says what to do.

Positions in metres, quaternions ``[w, x, y, z]`` as the tracker reports them (sensor to source, Hamilton; the same
convention ``ivc import`` uses for the Liberty logger CSVs), in the tracker's source frame.
"""

from __future__ import annotations

import select
import time as _time
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ivc.collect.stream import OpenedByWith, Sample, SourceEvent
from ivc.dipole import HEMISPHERES, hemisphere_vector
from ivc.errors import LiveError

#: per model: binary preamble, nominal frame rate (Hz), number of stations
MODELS = {"liberty": (b"LY", 240.0, 16), "patriot": (b"PA", 60.0, 2)}
#: output list items: 2 position (3 float32), 7 quaternion (4 float32), 9 frame count (uint32)
OUTPUT_LIST = "2,7,9"
CM = 0.01
#: the header, then the payload of OUTPUT_LIST, little-endian and packed
RECORD = np.dtype([("preamble", "S2"), ("station", "u1"), ("command", "u1"), ("error", "u1"), ("reserved", "u1"),
                   ("size", "<i2"), ("position", "<f4", 3), ("quaternion", "<f4", 4), ("frame", "<u4")])
HEADER_SIZE = 8
PAYLOAD_SIZE = RECORD.itemsize - HEADER_SIZE
#: initiating commands of a pose record: continuous ('C') or single ('P') output
POSE_COMMANDS = (ord("C"), ord("P"))
#: error bytes that mean "no error" (binary 0, ASCII space)
NO_ERROR = (0, 0x20)
#: a quaternion whose norm is further than this from 1 is not one the tracker sent intact
NORM_TOLERANCE = 1e-3
#: a frame count at most this far behind the last one is a repeated frame; further behind, a restarted counter
REPEAT_WINDOW = 8
#: a response to a command (not a pose record) is at most this long, from a station number at most this
MAX_RESPONSE = 1024
MAX_STATION = 32


def parse_records(buffer: bytes | bytearray, preambles: Sequence[bytes]) -> tuple[NDArray, list[tuple], int, int]:
    """Split a byte buffer into pose records, other binary responses and garbage.

    Returns ``(records, responses, garbage, consumed)``: the pose records (structured ``RECORD`` array, in order),
    the other responses as ``(preamble, station, command, error, payload)`` tuples, the number of garbage bytes
    skipped, and how many bytes of ``buffer`` were used (the rest is an incomplete record to keep for the next
    call). Runs of well-formed records are decoded with one ``numpy.frombuffer`` each; only garbage and command
    responses are walked byte-wise (``bytes.find``)."""
    data = bytes(buffer)
    size = len(data)
    pos = 0
    runs: list[NDArray] = []
    responses: list[tuple] = []
    garbage = 0
    codes = np.frombuffer(b"".join(preambles), dtype="S2")
    while pos < size:
        count = (size - pos) // RECORD.itemsize
        if count:
            run = np.frombuffer(data, dtype=RECORD, count=count, offset=pos)
            head, command = run["preamble"], run["command"]
            ok = ((head == codes[0]) if len(codes) == 1 else np.isin(head, codes))
            ok &= (run["size"] == PAYLOAD_SIZE) & (run["station"] >= 1)
            ok &= (command == POSE_COMMANDS[0]) | (command == POSE_COMMANDS[1])
            good = count if ok.all() else int(np.argmin(ok))
            if good:
                runs.append(run[:good])
                pos += good * RECORD.itemsize
                continue
        rest = size - pos
        if rest < 2 and any(p.startswith(data[pos:]) for p in preambles):
            break  # perhaps the first byte of a header
        if data[pos:pos + 2] in preambles:
            if rest < HEADER_SIZE:
                break
            head = data[pos:pos + HEADER_SIZE]
            length = int.from_bytes(head[6:8], "little", signed=True)
            if length == PAYLOAD_SIZE and head[3] in POSE_COMMANDS and head[2] >= 1:
                if rest < RECORD.itemsize:
                    break  # a pose record still arriving
            elif 0 <= length <= MAX_RESPONSE and head[2] <= MAX_STATION and head[5] == 0:
                if rest < HEADER_SIZE + length:
                    break
                responses.append((head[:2], head[2], head[3], head[4], data[pos + HEADER_SIZE:pos + HEADER_SIZE
                                                                              + length]))
                pos += HEADER_SIZE + length
                continue
        found = [i for i in (data.find(p, pos + 1) for p in preambles) if i >= 0]
        step = min(found) if found else (size - 1 if any(p[:1] == data[-1:] for p in preambles) else size)
        step = max(step, pos + 1)
        garbage += step - pos
        pos = step
    records = np.concatenate(runs) if runs else np.zeros(0, RECORD)
    return records, responses, garbage, pos


def _group(frame: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The distinct frame counts (sorted) and each record's index among them; a linear pass when the records
    arrive in frame order, as they do."""
    change = frame[1:] != frame[:-1]
    if frame.size and np.all(frame[1:] >= frame[:-1]):
        index = np.concatenate([[0], np.cumsum(change)])
        return frame[np.concatenate([[0], np.flatnonzero(change) + 1])], index
    return np.unique(frame, return_inverse=True)


def _positive(value) -> bool:
    try:
        return bool(np.isfinite(float(value)) and float(value) > 0)
    except (TypeError, ValueError):
        return False


def parse_stations(sensors: Sequence[str] | None, max_station: int = 16) -> list[int] | None:
    """Station numbers (1-based) from the step's sensor names, in the step's order; None keeps every station."""
    if sensors is None:
        return None
    stations = []
    for name in sensors:
        text = str(name).strip()
        if not text.isdigit() or not 1 <= int(text) <= max_station:
            raise LiveError(f"sensors={list(sensors)!r}: {name!r} is not a station number 1..{max_station}; name the "
                            "Polhemus stations (the numbered sensor sockets) in the step's order, sensor 0 first")
        stations.append(int(text))
    if len(set(stations)) != len(stations):
        raise LiveError(f"sensors={list(sensors)!r} names a station twice; give each station once")
    if not stations:
        raise LiveError("sensors=[] names no station; give the station numbers in the step's order, or None for all")
    return stations


class PolhemusSource(OpenedByWith):
    """A Polhemus Liberty or Patriot on ``port``, configured and streamed (see the module docstring).

    ``sensors``: station numbers as strings in the step's order (sensor 0 first), or None for every station the
    tracker streams, in station order. ``hemisphere``: the session's hemisphere (``"+x"`` ...). ``model``:
    ``"liberty"``, ``"patriot"`` or None to tell from the tracker's first records. ``rate_hz`` overrides the model's
    frame rate. ``stall_s``: a streaming tracker silent this long (host clock) is configured again; after
    ``reconfigure_limit`` silent rounds in a row the source gives up. ``retries`` / ``retry_wait_s``: how often and
    how far apart a vanished port is reopened. ``open_timeout_s``: how long :meth:`open` waits for the first frames.
    """

    def __init__(self, port: str, *, sensors: Sequence[str] | None = None, hemisphere: str = "+x",
                 model: str | None = None, baudrate: int = 115200, rate_hz: float | None = None, stall_s: float = 1.0,
                 reconfigure_limit: int = 5, retries: int = 5, retry_wait_s: float = 0.5, open_timeout_s: float = 5.0):
        if not isinstance(port, str) or not port:
            raise LiveError(f"port={port!r}: give the tracker's serial device, e.g. /dev/ttyUSB0")
        if hemisphere not in HEMISPHERES:
            raise LiveError(f"hemisphere={hemisphere!r}: use one of {', '.join(HEMISPHERES)} (the session's)")
        if model is not None and model not in MODELS:
            raise LiveError(f"model={model!r}: use one of {', '.join(MODELS)}, or None to tell from the tracker")
        for name, value in (("baudrate", baudrate), ("stall_s", stall_s), ("retry_wait_s", retry_wait_s),
                            ("open_timeout_s", open_timeout_s), ("rate_hz", 1.0 if rate_hz is None else rate_hz)):
            if not _positive(value):
                raise LiveError(f"{name}={value!r}: must be a positive number")
        for name, value, least in (("retries", retries, 0), ("reconfigure_limit", reconfigure_limit, 1)):
            if not isinstance(value, int | np.integer) or value < least:
                raise LiveError(f"{name}={value!r}: must be a whole number >= {least}")
        self.port = port
        self.hemisphere = hemisphere
        self.model = model
        self.baudrate = int(baudrate)
        self.stall_s = float(stall_s)
        self.reconfigure_limit = int(reconfigure_limit)
        self.retries = int(retries)
        self.retry_wait_s = float(retry_wait_s)
        self.open_timeout_s = float(open_timeout_s)
        self._rate_override = rate_hz
        self._wanted = parse_stations(sensors, max(n for _, _, n in MODELS.values()))
        self.stations: list[int] = []
        self.sensor_names: tuple[str, ...] = ()
        self.sample_rate_hz: float | None = rate_hz if rate_hz is not None else (
            MODELS[model][1] if model is not None else None)
        self._serial = None
        self._reset_state()

    # ------------------------------------------------------------------ set-up
    def _reset_state(self) -> None:
        self._buffer = bytearray()
        self._pending = np.zeros(0, RECORD)
        self._events: list[SourceEvent] = []
        self._last_frame: int | None = None  # device frame count of the last frame emitted
        self._last_time: float | None = None
        self._epoch: tuple[int, float] | None = None  # (frame count, time) that anchors the current time line
        self._new_epoch = True
        self._last_host: float | None = None  # host clock at the last frame emitted (only to bridge a reset)
        self._last_record_host = _time.monotonic()
        self._silent_rounds = 0
        self._failure: LiveError | None = None
        self._lookup = np.full(256, -1, dtype=np.int64)  # station number -> sensor index (-1: not recorded)
        self.counts = {"frames": 0, "repeated": 0, "lost": 0, "garbage_bytes": 0, "resets": 0, "reconnects": 0}

    @classmethod
    def from_spec(cls, argument: str, *, sensors: Sequence[str] | None = None, hemisphere: str = "+x",
                  **options) -> PolhemusSource:
        """``polhemus:DEVICE``: the tracker on serial device ``DEVICE`` (e.g. /dev/ttyUSB0); ``options`` are the
        constructor's keyword arguments."""
        return cls(argument, sensors=sensors, hemisphere=hemisphere, **options)

    def _open_port(self):
        import serial

        try:
            port = serial.Serial(self.port, self.baudrate, timeout=0, write_timeout=2.0)
            port.fileno()
            return port
        except (serial.SerialException, OSError, ValueError) as error:
            raise LiveError(f"cannot open the Polhemus serial port {self.port}: {error}. Check the device name "
                            "(ls /dev/ttyUSB* /dev/ttyACM*), that you may read it (the dialout group), that the "
                            "tracker is on and that no other program holds the port") from None

    def _write(self, command: bytes) -> None:
        self._serial.write(command)

    def _wait(self, timeout_s: float) -> bytes:
        """What the port has, waiting up to ``timeout_s`` (host clock) for the first byte."""
        if not select.select([self._serial.fileno()], [], [], max(timeout_s, 0.0))[0]:
            return b""
        return self._serial.read(max(1, self._serial.in_waiting))

    def _drain(self, quiet_s: float = 0.05, limit_s: float = 1.0) -> bytes:
        """What the tracker sends until it has been quiet ``quiet_s`` (at most ``limit_s``); the rest is dropped."""
        start = _time.monotonic()
        data = bytearray()
        while (chunk := self._wait(quiet_s)) and _time.monotonic() - start < limit_s:
            data += chunk
        self._serial.reset_input_buffer()
        return bytes(data)

    def configure(self, keep: bool = False) -> None:
        """Stop any output, set binary, centimetres, the hemisphere and the output list, then start continuous
        output (the commands of docs/polhemus.md). ``keep``: the frames still arriving after the stop belong to
        the stream being read (a re-configuration mid-stream) and are delivered, not dropped."""
        x, y, z = (int(v) for v in hemisphere_vector(self.hemisphere))
        self._write(b"P")
        tail = self._drain()
        if keep:
            self._buffer += tail
            records, _, _, used = parse_records(self._buffer, self._preambles())
            del self._buffer[:used]
            records = np.concatenate([self._pending, records]) if self._pending.size else records
            self._pending = np.zeros(0, RECORD)
            self._events.extend(self._frames(records, final=True))
        self._write(b"F1\rU1\r" + f"H*,{x},{y},{z}\r".encode() + f"O*,{OUTPUT_LIST}\r".encode())
        self._drain()
        self._buffer.clear()
        self._write(b"C\r")
        self._new_epoch = True
        self._last_record_host = _time.monotonic()

    def _preambles(self) -> list[bytes]:
        return [MODELS[self.model][0]] if self.model else [p for p, _, _ in MODELS.values()]

    def open(self) -> None:
        """Open the port, configure the tracker and wait for its first full frame (to learn its stations)."""
        if self._serial is not None:
            return
        self._reset_state()
        self._serial = self._open_port()
        try:
            self.configure()
            self._discover()
        except OSError as error:  # pyserial's SerialException is an OSError
            self.close()
            raise LiveError(f"the Polhemus port {self.port} failed while ivc configured the tracker ({error}): "
                            "check the cable and the port, then try again") from None
        except BaseException:
            self.close()
            raise

    def _discover(self) -> None:
        """Read until one frame has arrived whole (its records between two other frames'); set the model, rate and
        stations from it."""
        deadline = _time.monotonic() + self.open_timeout_s
        records = np.zeros(0, RECORD)
        while _time.monotonic() < deadline:
            new = self._receive(min(0.1, max(deadline - _time.monotonic(), 0.001)))
            if self._failure is not None:
                raise self._failure
            if new.size:
                records = np.concatenate([records, new])
                if np.unique(records["frame"]).size >= 3:
                    break
        frames = np.unique(records["frame"])
        if frames.size < 3:
            raise LiveError(f"no frame from the Polhemus tracker on {self.port} within {self.open_timeout_s:g} s of "
                            "configuring it: check that it is switched on with its source and a sensor plugged in, "
                            f"that the port and baud rate are right (baudrate={self.baudrate}), then try again")
        preamble = bytes(records["preamble"][0])
        model = next(m for m, (p, _, _) in MODELS.items() if p == preamble)
        if self.model is None:
            self.model = model
        if self.sample_rate_hz is None:
            self.sample_rate_hz = MODELS[self.model][1]
        first = records[records["frame"] == frames[1]]  # the first frame seen whole, from its start to its end
        present = sorted(set(int(s) for s in first["station"]))
        limit = MODELS[self.model][2]
        if self._wanted is not None:
            missing = [s for s in self._wanted if s not in present]
            if missing or max(self._wanted) > limit:
                raise LiveError(f"sensors: station(s) {missing or self._wanted} not streamed by the {self.model} on "
                                f"{self.port}, which streams stations {present}; plug the sensors in or name only "
                                "those stations")
            self.stations = list(self._wanted)
        else:
            self.stations = present
        self.sensor_names = tuple(str(s) for s in self.stations)
        self._lookup[:] = -1
        self._lookup[self.stations] = np.arange(len(self.stations))
        self._pending = records
        self._events.append(SourceEvent(
            "connected", f"Polhemus {self.model} on {self.port}: stations {', '.join(self.sensor_names)} at "
            f"{self.sample_rate_hz:g} Hz (binary, centimetres, hemisphere {self.hemisphere}, output list "
            f"{OUTPUT_LIST})"))

    # ------------------------------------------------------------------ reading
    def _receive(self, timeout_s: float) -> NDArray:
        """Read what the port has (waiting up to ``timeout_s`` for the first byte) and return its pose records."""
        import serial

        try:
            data = self._wait(timeout_s)
        except (serial.SerialException, OSError, ValueError) as error:
            self._reconnect(error)
            return np.zeros(0, RECORD)
        if not data:
            return np.zeros(0, RECORD)
        self._buffer += data
        records, responses, garbage, used = parse_records(self._buffer, self._preambles())
        del self._buffer[:used]
        if garbage:
            self.counts["garbage_bytes"] += garbage
            self._events.append(SourceEvent("garbage", f"skipped {garbage} bytes that were not Polhemus records "
                                            "(line noise, or text after a reset); resynchronised on the next header"))
        for _, station, command, error, payload in responses:
            if error not in NO_ERROR:
                text = payload.decode("ascii", "replace").strip()
                self._events.append(SourceEvent("info", f"the tracker answered command {chr(command)!r} (station "
                                                f"{station}) with error code {error}{': ' + text if text else ''}"))
        if records.size:
            self._last_record_host = _time.monotonic()
            self._silent_rounds = 0
        return records

    def _reconnect(self, error: Exception) -> None:
        """The port failed: reopen it (bounded), configure again, and report; LiveError when it stays gone."""
        self._events.append(SourceEvent("disconnected", f"the Polhemus port {self.port} failed ({error}); reopening"))
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - the port is already broken; closing is best effort
            pass
        self._serial = None
        self._flush_pending()
        last: Exception | None = None
        for attempt in range(1, self.retries + 1):
            _time.sleep(self.retry_wait_s)
            try:
                self._serial = self._open_port()
                self._buffer.clear()
                self.configure()
            except Exception as again:  # noqa: BLE001 - any failure here (LiveError, OSError, ...) is one more try
                last = again
                if self._serial is not None:
                    try:
                        self._serial.close()
                    except Exception:  # noqa: BLE001
                        pass
                    self._serial = None
                continue
            self.counts["reconnects"] += 1
            self._events.append(SourceEvent("reconnected", f"the Polhemus port {self.port} is back (try {attempt}) "
                                            "and the tracker was configured again"))
            return
        # raised by the next read, so that this one still delivers the frames read before the loss
        self._failure = LiveError(
            f"the Polhemus port {self.port} went away ({error}) and could not be reopened in {self.retries} tries "
            f"over {self.retries * self.retry_wait_s:g} s ({last if self.retries else 'no retries allowed'}): "
            "reconnect the tracker (cable, power, USB) and record the step again; the frames read before the loss "
            "were delivered")

    def _check_silence(self) -> None:
        """A tracker that stopped streaming (reset, power glitch) is configured again, a bounded number of times."""
        if _time.monotonic() - self._last_record_host < self.stall_s:
            return
        self._silent_rounds += 1
        if self._silent_rounds > self.reconfigure_limit:
            raise LiveError(f"the Polhemus tracker on {self.port} has sent no frame for "
                            f"{self._silent_rounds * self.stall_s:.1f} s despite {self.reconfigure_limit} "
                            "re-configurations: check that it is on, its source and sensors plugged in, then record "
                            "the step again")
        self.counts["resets"] += 1
        self._events.append(SourceEvent("reset", f"the tracker sent nothing for {self.stall_s:g} s (reset or power "
                                        "glitch?); it was configured again (binary, cm, hemisphere "
                                        f"{self.hemisphere}, continuous)", time=self._last_time))
        try:
            self.configure(keep=True)
        except OSError as error:  # the port went away while silent
            self._reconnect(error)

    def read(self, timeout_s: float) -> list[Sample | SourceEvent]:
        """The frames (and events) that arrived, waiting at most ``timeout_s`` for the first bytes."""
        if self._failure is not None:
            raise self._failure
        if self._serial is None and not self._events:
            raise LiveError("open the Polhemus source before reading it (use it in a with statement)")
        new = self._receive(timeout_s) if self._serial is not None else np.zeros(0, RECORD)
        records = np.concatenate([self._pending, new]) if self._pending.size else new
        self._pending = np.zeros(0, RECORD)
        out: list[Sample | SourceEvent] = list(self._events)
        self._events.clear()
        out.extend(self._frames(records))
        out.extend(self._events)
        self._events.clear()
        if self._serial is not None:
            self._check_silence()
            out.extend(self._events)
            self._events.clear()
        return out

    def _flush_pending(self) -> None:
        """Deliver the incomplete last frame as it is (its missing stations invalid), e.g. before a reset."""
        if self._pending.size:
            records, self._pending = self._pending, np.zeros(0, RECORD)
            self._events.extend(self._frames(records, final=True))

    def _frames(self, records: NDArray, final: bool = False) -> list[Sample | SourceEvent]:
        """Samples from pose records in arrival order (vectorised over the records); keeps the last, incomplete
        frame pending unless ``final``."""
        if not records.size:
            return []
        records = records[self._lookup[records["station"]] >= 0]
        if not records.size:
            return []
        frame = records["frame"].astype(np.int64)
        out: list[Sample | SourceEvent] = []
        # a frame count far behind the running maximum starts a new time line (the tracker was reset)
        base = self._last_frame if (self._last_frame is not None and not self._new_epoch) else frame[0]
        running = np.maximum.accumulate(np.concatenate([[base], frame]))[:-1]
        restarts = np.flatnonzero(frame < running - REPEAT_WINDOW)
        if restarts.size:
            cut = int(restarts[0])
            out.extend(self._segment(records[:cut], final=True))
            if not self._new_epoch:
                self.counts["resets"] += 1
                out.append(SourceEvent("reset", f"the tracker's frame count went back from {self._last_frame} to "
                                       f"{int(frame[cut])}: it was reset; its time line continues",
                                       time=self._last_time))
            self._new_epoch = True
            out.extend(self._frames(records[cut:], final))
            return out
        out.extend(self._segment(records, final))
        return out

    def _segment(self, records: NDArray, final: bool) -> list[Sample | SourceEvent]:
        """Samples of records on one time line (no restart of the frame count among them)."""
        if not records.size:
            return []
        rate = float(self.sample_rate_hz)
        frame = records["frame"].astype(np.int64)
        if self._new_epoch:
            # after a re-configuration a counter that ran on keeps the time line; the first time line starts at the
            # frame count itself, and one after a restarted counter just after the last frame, by the whole frames
            # the host saw pass (the tracker's own clock restarted and cannot say)
            if self._last_frame is None or frame[0] <= self._last_frame:
                if self._last_time is None:
                    start = float(frame[0]) / rate
                else:
                    gap = _time.monotonic() - self._last_host
                    start = self._last_time + max(1.0, round(gap * rate)) / rate
                self._epoch = (int(frame[0]), start)
                self._last_frame = int(frame[0]) - 1
            self._new_epoch = False
        n = len(self.stations)
        fresh = frame > self._last_frame
        repeated = 0
        if not fresh.all():  # frames already delivered, sent again
            repeated = int(np.count_nonzero(~fresh))
            records, frame = records[fresh], frame[fresh]
        sensor = self._lookup[records["station"]]
        frames, index = _group(frame)
        slot = index * n + sensor
        count = np.bincount(slot, minlength=frames.size * n)
        if count.size and count.max() > 1:  # a frame's record sent twice: keep the first
            _, first = np.unique(slot, return_index=True)
            first.sort()
            repeated += frame.size - first.size
            records, frame, sensor = records[first], frame[first], sensor[first]
            frames, index = _group(frame)
            count = np.bincount(index * n + sensor, minlength=frames.size * n)
        if repeated:
            self.counts["repeated"] += repeated
        if not records.size:
            return []
        present = count.reshape(frames.size, n) > 0
        if not final and not present[-1].all():
            hold = index == frames.size - 1
            self._pending = records[hold]
            frames, present = frames[:-1], present[:-1]
            records, index, sensor = records[~hold], index[~hold], sensor[~hold]
            if not frames.size:
                return []
        position = np.full((frames.size, n, 3), np.nan)
        quaternion = np.full((frames.size, n, 4), np.nan)
        position[index, sensor] = records["position"].astype(np.float64) * CM
        quaternion[index, sensor] = records["quaternion"].astype(np.float64)
        error = np.zeros((frames.size, n), np.uint8)
        error[index, sensor] = records["error"]
        norm = np.linalg.norm(quaternion, axis=-1)
        flagged = (error != NO_ERROR[0]) & (error != NO_ERROR[1])
        valid = (present & ~flagged & np.all(np.isfinite(position), axis=-1)
                 & np.any(position != 0.0, axis=-1) & (np.abs(norm - 1.0) <= NORM_TOLERANCE))
        position[~valid] = np.nan
        quaternion[~valid] = np.nan
        events: list[Sample | SourceEvent] = []
        if flagged.any():
            coded = np.unique(error[present & flagged])
            names = ", ".join(repr(chr(c)) if 32 < c < 127 else str(int(c)) for c in coded)
            events.append(SourceEvent("info", f"the tracker flagged samples with error code(s) {names} (distortion "
                                      "or a real-time error): stored as invalid"))
        lost = int(np.sum(np.diff(np.concatenate([[self._last_frame], frames])) - 1))
        if lost > 0 and self._last_frame is not None:
            self.counts["lost"] += lost
            events.append(SourceEvent("info", f"{lost} tracker frame(s) never arrived (frame counts "
                                      f"{self._last_frame + 1}..{int(frames[-1]) - 1})"))
        f0, t0 = self._epoch
        times = t0 + (frames - f0) / rate
        host = _time.monotonic()
        samples = [Sample(time=float(times[i]), valid=valid[i], position=position[i], quaternion=quaternion[i],
                          frame=int(frames[i]), host_time=host) for i in range(frames.size)]
        self._last_frame = int(frames[-1])
        self._last_time = float(times[-1])
        self._last_host = host
        self.counts["frames"] += frames.size
        return events + samples

    def close(self) -> None:
        """Stop continuous output and close the port."""
        if self._serial is not None:
            try:
                self._serial.write(b"P")
                self._serial.flush()
            except Exception:  # noqa: BLE001 - closing a port that may already be gone is best effort
                pass
            try:
                self._serial.close()
            except Exception:  # noqa: BLE001
                pass
        self._serial = None
