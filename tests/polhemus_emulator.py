"""An emulated Polhemus Liberty / Patriot on a pseudo-terminal, written from the public protocol (docs/polhemus.md).

The emulator owns a pty pair (``os.openpty``) and runs a thread that plays the tracker's side: it parses the
commands ivc (or anyone) writes to :attr:`PolhemusEmulator.path` and streams the given poses as the device would.
It is deliberately written apart from ``ivc.collect.polhemus_serial`` (its own record layout and command parser),
so that a mistake in one is not mirrored in the other.

Commands understood (case-insensitive; ``\\r`` ends a command, ``P`` and ctrl-Y act at once):
``F0``/``F1`` ASCII / binary output, ``U0``/``U1`` inches / centimetres, ``H*,x,y,z`` or ``Hn,x,y,z`` hemisphere,
``O*,i,j,...`` or ``On,...`` output list (items 0 space, 1 CR LF, 2 position, 7 quaternion, 8 time stamp in ms,
9 frame count), ``C`` continuous output, ``P`` stop continuous output (or, when stopped, one record), ctrl-Y reset.
Anything else is answered with an error record (code 1 invalid command, 3 invalid parameter).

Binary record per station: ``LY``/``PA``, station, initiating command ('C' or 'P'), error byte, reserved 0,
int16 payload size, then the output list's items, little-endian (float32 values, uint32 counters).

Quirks, keyed by the index of the truth frame they hit: ``repeat`` (frame sent twice), ``dropouts`` ((frame,
sensor) pairs reported at (0, 0, 0)), ``errors`` ({(frame, sensor): error byte}, e.g. a distortion flag),
``garbage`` ({frame: bytes written before it}), ``pauses`` ({frame: seconds} the line stalls before it, the frame
count running on), ``reset_at`` (before that frame the tracker reboots: it prints a line of text, forgets its
configuration and stops until configured again; its frame count restarts at 0) and ``close_at`` (before that frame
the port vanishes; with ``close_when``, once that event is set).
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import termios
import threading
import time
import tty
from collections.abc import Iterable

import numpy as np

INCH = 0.0254
MODELS = {"liberty": (b"LY", 240.0, 16), "patriot": (b"PA", 60.0, 2)}
#: output list item -> (field name, numpy type, count)
ITEMS = {0: ("space", "S1", 1), 1: ("crlf", "S2", 1), 2: ("position", "<f4", 3), 7: ("quaternion", "<f4", 4),
         8: ("timestamp", "<u4", 1), 9: ("frame", "<u4", 1)}
DEFAULT_LIST = (2, 7, 1)
ERROR_INVALID_COMMAND, ERROR_INVALID_PARAMETER = 1, 3
BANNER = b"\r\nsystem reset - initialising, please wait\r\n"


def record_dtype(items: Iterable[int]) -> np.dtype:
    """The packed binary record (header and payload) of an output list."""
    fields = [("pre", "S2"), ("station", "u1"), ("command", "u1"), ("error", "u1"), ("reserved", "u1"),
              ("size", "<i2")]
    for n, item in enumerate(items):
        name, kind, count = ITEMS[item]
        fields.append((f"{name}_{n}", kind) if count == 1 else (f"{name}_{n}", kind, count))
    return np.dtype(fields)


class PolhemusEmulator:
    """A tracker streaming ``positions`` (F, N, 3) m and ``quaternions`` (F, N, 4) (``valid`` (F, N), False = a
    dropout) for stations ``stations`` (default 1..N) in the source frame.

    ``rate_hz``: pace frames by the host clock at this rate; None streams as fast as the reader takes them.
    ``loop``: replay the truth frames cyclically; ``max_frames``: stop after that many streamed frames.
    :attr:`sent` lists every streamed frame as (epoch, frame count, truth index); :attr:`done` is set once
    ``max_frames`` (or the truth) has been written out."""

    def __init__(self, positions, quaternions, valid=None, *, model: str = "liberty", stations=None,
                 rate_hz: float | None = None, loop: bool = False, max_frames: int | None = None, chunk: int = 64,
                 first_frame: int = 1000, repeat=(), dropouts=(), errors=None, garbage=None, reset_at=None,
                 close_at=None, close_when: threading.Event | None = None, pauses=None):
        self.positions = np.asarray(positions, dtype=float)
        self.quaternions = np.asarray(quaternions, dtype=float)
        frames, n = self.positions.shape[:2]
        self.preamble, self.nominal_rate, limit = MODELS[model]
        self.model = model
        self.stations = np.asarray(stations if stations is not None else range(1, n + 1), dtype=np.uint8)
        assert len(self.stations) == n <= limit
        self.rate_hz = rate_hz
        self.loop = loop
        self.max_frames = max_frames if max_frames is not None else (None if loop else frames)
        self.chunk = chunk
        self.dropout = ~np.asarray(valid, bool) if valid is not None else np.zeros((frames, n), bool)
        for f, s in dropouts:
            self.dropout[f, s] = True
        self.error = np.zeros((frames, n), np.uint8)
        for (f, s), code in (errors or {}).items():
            self.error[f, s] = code
        self.repeats = np.ones(frames, np.int64)
        self.repeats[list(repeat)] = 2
        self.garbage = dict(garbage or {})
        self.pauses = dict(pauses or {})
        self._paused_until: float | None = None
        self.reset_at = reset_at
        self.close_at = close_at
        self.close_when = close_when
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.sent: list[tuple[int, int, int]] = []
        self.commands: list[bytes] = []
        self.done = threading.Event()
        self.closed = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="polhemus-emulator", daemon=True)
        self._first_frame = first_frame
        self._defaults()
        self.epoch = 0
        self.frame_count = first_frame
        self.index = 0  # next truth frame
        self.streamed = 0
        self._vanish_by: float | None = None
        self.streamed_in_run = 0  # frames since the last 'C' (paces real-rate output)

    # ------------------------------------------------------------------ state
    def _defaults(self) -> None:
        self.binary = False
        self.metric = False
        self.hemisphere = np.array([1.0, 0.0, 0.0])
        self.lists = {int(s): DEFAULT_LIST for s in self.stations}
        self.continuous = False
        self._out = bytearray()
        self._command = bytearray()
        self._start: float | None = None

    def start(self) -> PolhemusEmulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10)
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self.closed.set()

    def __enter__(self) -> PolhemusEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ commands
    def _error(self, command: bytes, code: int, text: str) -> None:
        letter = command[:1] or b"?"
        if self.binary:
            payload = text.encode()
            self._out += self.preamble + bytes([0, letter[0], code, 0]) + len(payload).to_bytes(2, "little") + payload
        else:
            self._out += b"00" + letter + b" " + text.encode() + b"\r\n"

    def _stations(self, field: bytes) -> list[int] | None:
        if field == b"*":
            return [int(s) for s in self.stations]
        if field.isdigit() and int(field) in self.lists:
            return [int(field)]
        return None

    def _execute(self, command: bytes) -> None:
        self.commands.append(command)
        if not command:
            return
        letter, rest = command[:1].upper(), command[1:]
        if letter == b"F" and rest in (b"0", b"1"):
            self.binary = rest == b"1"
        elif letter == b"U" and rest in (b"0", b"1"):
            self.metric = rest == b"1"
        elif letter == b"C" and not rest:
            self.continuous = True
            self._start = None
        elif letter == b"H":
            parts = rest.split(b",")
            stations = self._stations(parts[0]) if parts else None
            try:
                vector = np.array([float(p) for p in parts[1:]])
            except ValueError:
                vector = np.zeros(0)
            if stations is None or vector.shape != (3,) or not np.any(vector):
                self._error(command, ERROR_INVALID_PARAMETER, "invalid parameter")
            else:
                self.hemisphere = vector / np.linalg.norm(vector)
        elif letter == b"O":
            parts = rest.split(b",")
            stations = self._stations(parts[0]) if parts else None
            try:
                items = tuple(int(p) for p in parts[1:])
            except ValueError:
                items = ()
            if stations is None or not items or any(i not in ITEMS for i in items):
                self._error(command, ERROR_INVALID_PARAMETER, "invalid parameter")
            else:
                for s in stations:
                    self.lists[s] = items
        else:
            self._error(command, ERROR_INVALID_COMMAND, "invalid command")

    def _commands(self, data: bytes) -> None:
        for byte in data:
            if byte == 0x19:  # ctrl-Y: reset
                self._reset()
            elif byte == 0x0D:
                command = bytes(self._command)
                self._command.clear()
                self._execute(command)
            elif not self._command and byte in b"Pp":
                self.commands.append(b"P")
                if self.continuous:
                    self.continuous = False
                else:
                    self._out += self._pack([self.index % len(self.positions)], [self.frame_count], b"P")
            elif byte != 0x0A:
                self._command.append(byte)

    def _reset(self) -> None:
        self._defaults()
        self.epoch += 1
        self.frame_count = 0
        self._out += BANNER

    # ------------------------------------------------------------------ records
    def _pack(self, truth: list[int] | np.ndarray, counts, command: bytes = b"C") -> bytes:
        """The records of the truth frames ``truth`` with frame counts ``counts``, each station in turn."""
        truth = np.asarray(truth, dtype=np.int64)
        counts = np.asarray(counts, dtype=np.int64)
        position = self.positions[truth] / (0.01 if self.metric else INCH)
        flip = np.einsum("fnk,k->fn", position, self.hemisphere) < 0
        position[flip] *= -1.0
        quaternion = self.quaternions[truth].copy()
        drop = self.dropout[truth]
        position[drop] = 0.0
        quaternion[drop] = (1.0, 0.0, 0.0, 0.0)
        lists = {self.lists[int(s)] for s in self.stations}
        if not self.binary:
            return self._ascii(truth, counts, position, quaternion, command)
        if len(lists) == 1:
            items = lists.pop()
            records = np.zeros((truth.size, len(self.stations)), record_dtype(items))
            self._fill(records, items, truth, counts, position, quaternion, command)
            records = np.repeat(records, self.repeats[truth], axis=0) if command == b"C" else records
            return records.tobytes()
        out = bytearray()
        for f in range(truth.size):
            for _repeat in range(self.repeats[truth[f]] if command == b"C" else 1):
                for s, station in enumerate(self.stations):
                    items = self.lists[int(station)]
                    record = np.zeros((1, 1), record_dtype(items))
                    self._fill(record, items, truth[f:f + 1], counts[f:f + 1], position[f:f + 1, s:s + 1],
                               quaternion[f:f + 1, s:s + 1], command, s)
                    out += record.tobytes()
        return bytes(out)

    def _fill(self, records, items, truth, counts, position, quaternion, command, only=None) -> None:
        stations = self.stations if only is None else self.stations[only:only + 1]
        error = self.error[truth] if only is None else self.error[truth][:, only:only + 1]
        records["pre"] = self.preamble
        records["station"] = stations
        records["command"] = command[0]
        records["error"] = error
        records["size"] = records.dtype.itemsize - 8
        for n, item in enumerate(items):
            name = f"{ITEMS[item][0]}_{n}"
            if item == 0:
                records[name] = b" "
            elif item == 1:
                records[name] = b"\r\n"
            elif item == 2:
                records[name] = position.astype(np.float32)
            elif item == 7:
                records[name] = quaternion.astype(np.float32)
            elif item == 8:
                records[name] = (counts * 1000 / self.nominal_rate).astype(np.uint32)[:, None]
            elif item == 9:
                records[name] = counts.astype(np.uint32)[:, None]

    def _ascii(self, truth, counts, position, quaternion, command) -> bytes:
        lines = []
        for f in range(truth.size):
            for s, station in enumerate(self.stations):
                code = self.error[truth[f], s]
                text = f"0{station}{chr(code) if code else ' '}"
                for item in self.lists[int(station)]:
                    if item == 2:
                        text += "".join(f"{v:10.4f}" for v in position[f, s])
                    elif item == 7:
                        text += "".join(f"{v:9.5f}" for v in quaternion[f, s])
                    elif item in (8, 9):
                        text += f" {int(counts[f])}"
                    elif item == 0:
                        text += " "
                    elif item == 1:
                        text += "\r\n"
                lines.append(text)
        return "".join(lines).encode()

    # ------------------------------------------------------------------ the device's loop
    def _due(self) -> int:
        """How many frames may be generated now."""
        if self.rate_hz is None:
            return self.chunk if len(self._out) < 1 << 16 else 0
        now = time.monotonic()
        if self._start is None:
            self._start = now - self.streamed_in_run / self.rate_hz
        return max(0, int((now - self._start) * self.rate_hz) + 1 - self.streamed_in_run)

    def _unread(self) -> int:
        """Bytes written to the line that the reader has not taken yet."""
        return struct.unpack("i", fcntl.ioctl(self.slave, termios.FIONREAD, b"\0\0\0\0"))[0]

    def _vanish_deadline(self) -> float:
        if self._vanish_by is None:
            self._vanish_by = time.monotonic() + 10.0
        return self._vanish_by

    def _next_special(self) -> int | None:
        marks = [m for m in (self.reset_at, self.close_at, *self.garbage, *self.pauses)
                 if m is not None and m >= self.index]
        return min(marks) if marks else None

    def _generate(self) -> None:
        frames = len(self.positions)
        if self.max_frames is not None and self.streamed >= self.max_frames:
            return
        due = self._due()
        if not due:
            return
        special = self._next_special()
        if special == self.index:
            if self._out:
                return  # finish the transmission under way first
            if self.index in self.pauses:
                if self._paused_until is None:
                    self._paused_until = time.monotonic() + self.pauses[self.index]
                if time.monotonic() < self._paused_until:
                    return  # the line stalls (the counter runs on: frames of the pause are never sent)
                self.frame_count += int(round(self.pauses.pop(self.index) * self.nominal_rate))
                self._paused_until = None
                return
            if self.index in self.garbage:
                self._out += self.garbage.pop(self.index)
                return
            if self.index == self.reset_at:
                self.reset_at = None
                self._reset()
                return
            if self.index == self.close_at:
                if self.close_when is not None and not self.close_when.is_set():
                    return  # the test says when
                if self._unread() and time.monotonic() < self._vanish_deadline():
                    return  # let the reader take what is on the line, then vanish
                self.close_at = None
                raise _Vanish
        stop = self.index + due
        if special is not None:
            stop = min(stop, special)
        if self.max_frames is not None:
            stop = min(stop, self.index + self.max_frames - self.streamed)
        if not self.loop:
            stop = min(stop, frames)
        if stop <= self.index:
            return
        truth = np.arange(self.index, stop)
        counts = self.frame_count + np.arange(truth.size)
        self._out += self._pack(truth % frames, counts)
        with self._lock:
            self.sent.extend((self.epoch, int(c), int(t)) for c, t in zip(counts, truth % frames, strict=True))
        self.index = stop
        self.frame_count += truth.size
        self.streamed += truth.size
        self.streamed_in_run += truth.size

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self.continuous:
                    self._generate()
                if self._finished() and not self._out:
                    self.done.set()
                want_write = [self.master] if self._out else []
                streaming = self.continuous and not self._finished()
                if self.rate_hz is not None:
                    timeout = 0.5 / self.rate_hz if streaming else 0.05
                else:
                    busy = streaming and len(self._out) < 1 << 16 and self._next_special() != self.index
                    timeout = 0.0 if busy else 0.05
                readable, writable, _ = select.select([self.master], want_write, [], timeout)
                if readable:
                    try:
                        data = os.read(self.master, 4096)
                    except BlockingIOError:
                        data = b""
                    if data:
                        was = self.continuous
                        self._commands(data)
                        if self.continuous and not was:
                            self.streamed_in_run = 0
                if writable and self._out:
                    try:
                        written = os.write(self.master, self._out)
                    except BlockingIOError:
                        written = 0
                    del self._out[:written]
        except _Vanish:
            self._close_fds()
        except OSError:
            if not self._stop.is_set():
                raise

    def _finished(self) -> bool:
        if self.max_frames is not None:
            return self.streamed >= self.max_frames
        return not self.loop and self.index >= len(self.positions)

    def sent_frames(self) -> list[tuple[int, int, int]]:
        with self._lock:
            return list(self.sent)


class _Vanish(Exception):
    """The emulated port disappears (cable pulled)."""


def smooth_poses(frames: int, sensors: int, rate_hz: float = 240.0, seed: int = 0):
    """Poses (frames, sensors) of sensors wandering in the +x hemisphere: positions (m) and unit quaternions."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None] / rate_hz
    phase = rng.uniform(0, 2 * np.pi, (1, sensors, 3))
    centre = np.array([0.35, 0.0, 0.05]) + rng.uniform(-0.1, 0.1, (1, sensors, 3))
    position = centre + 0.08 * np.sin(2 * np.pi * 0.3 * t + phase)
    angle = 0.9 * np.sin(2 * np.pi * 0.2 * t[..., 0] + phase[..., 0])
    axis = np.stack([np.cos(phase[..., 1]), np.sin(phase[..., 1]) * np.cos(phase[..., 2]),
                     np.sin(phase[..., 1]) * np.sin(phase[..., 2])], axis=-1)
    axis = np.broadcast_to(axis, (frames, sensors, 3))
    quaternion = np.concatenate([np.cos(angle / 2)[..., None], np.sin(angle / 2)[..., None] * axis], axis=-1)
    return position, quaternion
