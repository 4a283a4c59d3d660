"""OpenIGTLink framing on a byte stream, and the two message types pyigtl lacks (TDATA, NDARRAY).

pyigtl supplies the message classes and the CRC-64; its client and server threads are not used:
they poll with 10 ms socket timeouts and keep only the newest message per device, which would
add latency and drop frames at 240 Hz. :class:`Framer` splits a stream into whole messages,
checks each body's CRC-64, and resynchronises after garbage. The tracking messages of the hot
path (TRANSFORM, NDARRAY in; TRANSFORM out) are decoded and encoded here with NumPy: through
pyigtl's generic objects they cost more than the correction itself (benchmarks/bench_live.py).
"""

from __future__ import annotations

import math
import re
import struct
import time
from dataclasses import dataclass
from urllib.parse import urlparse

import numpy as np
from pyigtl.messages import CRC64, MessageBase, message_type_to_class_constructor

from ivc.errors import InputError

HEADER = struct.Struct("> H 12s 20s II Q Q")
HEADER_SIZE = HEADER.size  # 58
#: the largest body of each small message type (bytes): a header claiming more is taken as garbage. A
#: tracking message is a few hundred bytes; 64 KiB leaves room for any v2 metadata.
BODY_LIMITS = {kind: 1 << 16 for kind in ("TRANSFORM", "NDARRAY", "TDATA", "QTDATA", "POSITION", "QTRANS",
                                          "STATUS", "STT_TDATA", "STP_TDATA", "RTS_TDATA", "GET_TDATA", "CAPABILITY",
                                          "GET_TRANS", "GET_STATUS", "STRING", "COMMAND", "RTS_COMMAND")}
#: the largest body of any other type (IMAGE, VIDEO, POLYDATA, ...): a 4K RGBA video frame is 33 MB
MAX_BODY = 1 << 28
#: seconds a header may wait for its body before the framer looks past it for the next whole, CRC-valid message
BODY_TIMEOUT_S = 0.1
DEFAULT_PORT = 18944
#: bodies at least this long (bytes) have their CRC computed piecewise as they arrive
INCREMENTAL_CRC_BYTES = 1 << 16
_CRC_START = CRC64(b"")
#: where a header may start: version 1-3, then a type name's first character
_CANDIDATE = re.compile(rb"\x00[\x01-\x03][0-9:;<=>?@A-Z_]")


def parse_url(url: str) -> tuple[str, int]:
    """``igtl://HOST:PORT`` (or ``HOST:PORT``) → (host, port)."""
    parsed = urlparse(url if "://" in url else f"igtl://{url}")
    if parsed.scheme != "igtl" or not parsed.hostname:
        raise InputError(f"expected igtl://HOST:PORT, got {url!r}")
    return parsed.hostname, parsed.port or DEFAULT_PORT


@dataclass
class Frame:
    """One whole message from the stream. ``payload``: the 4x4 matrix of a TRANSFORM (translation in the
    stream's unit), the array of an NDARRAY, else None."""

    message_type: str
    device_name: str
    timestamp: float
    payload: np.ndarray | None


_EXTENDED = struct.Struct("> H H I I")
_TRANSFORM = np.dtype(">f4")


def _content(version: int, body: bytes) -> bytes:
    """The message content of a body: without the v2 extended header and metadata."""
    if version < 2:
        return body
    extended, meta_header, meta_body, _ = _EXTENDED.unpack_from(body)
    return body[extended:len(body) - meta_header - meta_body]


def decode_transform(content: bytes) -> np.ndarray:
    v = np.frombuffer(content, _TRANSFORM, 12).astype(float)
    m = np.eye(4)
    m[:3, :3] = v[:9].reshape(3, 3).T  # column-major rotation
    m[:3, 3] = v[9:]
    return m


def decode_ndarray(content: bytes) -> np.ndarray:
    scalar, ndim = struct.unpack_from("> B B", content)
    if scalar not in NDArrayMessage.TYPES:
        raise InputError(f"NDARRAY scalar type {scalar} is not supported")
    shape = struct.unpack_from(f"> {ndim}H", content, 2)
    dtype = np.dtype(NDArrayMessage.TYPES[scalar])
    data = content[2 + 2 * ndim:]
    if len(data) != dtype.itemsize * math.prod(shape):
        raise InputError("NDARRAY size does not match its shape")
    return np.frombuffer(data, dtype).reshape(shape).astype(float)


_DECODERS = {"TRANSFORM": decode_transform, "NDARRAY": decode_ndarray}


class Framer:
    """Feed bytes with :meth:`feed`; take whole, CRC-checked messages from :meth:`messages`.

    TRANSFORM and NDARRAY contents are decoded here (the hot path; other types, IMAGE included,
    are passed on undecoded after their body, of the size the header declares, has passed its
    CRC). One header cannot stall the stream: a small type's body is bounded (``BODY_LIMITS``)
    and a header whose body has not arrived within ``timeout_s`` while a whole, CRC-valid
    message follows it is dropped as garbage and the framer resynchronises on that message.
    ``garbage`` counts the bytes skipped to find the next valid header; ``bad`` the messages
    whose content could not be decoded.
    """

    def __init__(self, timeout_s: float = BODY_TIMEOUT_S):
        self.buffer = bytearray()
        self.garbage = 0
        self.bad = 0
        self.timeout_s = float(timeout_s)
        self._waiting_since: float | None = None  # when the header at the buffer's start began to wait
        self._resync_from = 1  # where the search past a waiting header resumes (nothing before it can start one)
        self._partial: tuple[int, int] | None = None  # (CRC so far, body bytes covered) of the header at 0

    def feed(self, data: bytes) -> None:
        self.buffer += data

    @property
    def waiting(self) -> bool:
        """Whether a header waits for its body (call :meth:`messages` again later: its timeout may resync)."""
        return self._waiting_since is not None

    def clear(self) -> None:
        """Forget any partial message (after a reconnection)."""
        self.buffer.clear()
        self._waiting_since = None
        self._resync_from = 1
        self._partial = None

    def _header_at(self, at: int):
        version, kind, device, seconds, fraction, size, crc = HEADER.unpack_from(self.buffer, at)
        if version not in (1, 2, 3):
            return None
        kind = kind.rstrip(b"\0")
        if not kind or not all(48 <= c < 91 or c == 95 for c in kind):  # 0-9, :;<=>?@, A-Z, _
            return None
        kind = kind.decode()
        if size > BODY_LIMITS.get(kind, MAX_BODY) or (version >= 2 and size < _EXTENDED.size):
            return None
        return version, kind, device, seconds, fraction, size, crc

    def _advance_crc(self) -> None:
        """Extend the running CRC of a large body waiting at the buffer's start over the bytes that arrived,
        so that a video frame's CRC costs nothing extra when its last bytes come (and tracking messages
        behind it do not wait for it)."""
        header = self._header_at(0)
        if header is None or header[5] < INCREMENTAL_CRC_BYTES:
            return
        running, done = self._partial or (_CRC_START, 0)
        available = min(len(self.buffer) - HEADER_SIZE, header[5])
        if available > done:
            with memoryview(self.buffer) as view, view[HEADER_SIZE + done:HEADER_SIZE + available] as part:
                running = CRC64(part, running)
            self._partial = (running, available)

    def _next_candidate(self, start: int) -> int:
        """Position of the next possible header at or after ``start`` (or where scanning may resume)."""
        match = _CANDIDATE.search(self.buffer, start)
        if match is None:  # keep the last two bytes: a header may begin there
            return max(start, len(self.buffer) - 2)
        return match.start()

    def _whole_message_at(self, at: int) -> bool:
        header = self._header_at(at)
        if header is None:
            return False
        end = at + HEADER_SIZE + header[5]
        return end <= len(self.buffer) and CRC64(bytes(self.buffer[at + HEADER_SIZE:end])) == header[6]

    def _resync_past_stalled_header(self) -> int | None:
        """Where the first whole, CRC-valid message after the header at 0 starts, or None. The search resumes
        where the last one left off (at the first header still waiting for its body), so a large body
        arriving slowly is scanned once, not once per read."""
        at = self._resync_from
        while len(self.buffer) - at >= HEADER_SIZE:
            at = self._next_candidate(at)
            if len(self.buffer) - at < HEADER_SIZE:
                break
            header = self._header_at(at)
            if header is not None:
                end = at + HEADER_SIZE + header[5]
                if end > len(self.buffer):  # may be whole later: resume here next time
                    self._resync_from = at
                    return None
                if CRC64(bytes(self.buffer[at + HEADER_SIZE:end])) == header[6]:
                    return at
            at += 1
        self._resync_from = max(1, len(self.buffer) - HEADER_SIZE + 1)
        return None

    def messages(self, now: float | None = None) -> list[Frame]:
        """The whole messages in the buffer, in order; ``now`` (time.monotonic) for the body timeout."""
        out = []
        at = 0
        buf = self.buffer
        while len(buf) - at >= HEADER_SIZE:
            header = self._header_at(at)
            if header is None:
                skip = self._next_candidate(at + 1)
                self.garbage += skip - at
                at = skip
                continue
            version, kind, device, seconds, fraction, size, crc = header
            end = at + HEADER_SIZE + size
            if len(buf) < end:
                break  # wait for the rest of the body
            if at == 0 and self._partial is not None:  # the CRC of the body's start, computed as it arrived
                running, done = self._partial
            else:
                running, done = _CRC_START, 0
            with memoryview(buf) as view, view[at + HEADER_SIZE + done:end] as rest:
                running = CRC64(rest, running)
            self._partial = None
            if running != crc:
                skip = self._next_candidate(at + 1)
                self.garbage += skip - at
                at = skip
                continue
            payload = None
            decoder = _DECODERS.get(kind)
            if decoder is not None:  # the small tracking messages: a copy of the body to decode
                try:
                    payload = decoder(_content(version, bytes(buf[at + HEADER_SIZE:end])))
                except (struct.error, ValueError):
                    self.bad += 1
            name = device.rstrip(b"\0").decode(errors="replace")
            out.append(Frame(kind, name, seconds + fraction / 2.0**32, payload))
            at = end
        if at:
            del buf[:at]
            self._waiting_since = None
            self._resync_from = 1
            self._partial = None
        if len(buf) >= HEADER_SIZE:  # a header waits for its body
            self._advance_crc()
            now = time.monotonic() if now is None else now
            if self._waiting_since is None:
                self._waiting_since = now
            elif now - self._waiting_since > self.timeout_s:
                resume = self._resync_past_stalled_header()
                if resume is not None:
                    self.garbage += resume
                    del buf[:resume]
                    self._partial = None
                    self._waiting_since = None
                    self._resync_from = 1
                    out += self.messages(now)
        return out


def _stamp(timestamp: float) -> tuple[int, int]:
    seconds = int(timestamp)
    return seconds, min(int((timestamp - seconds) * 2.0**32), 0xFFFFFFFF)


def encode_transforms(names: list[str], stamps: list[float], matrices: np.ndarray,
                      metadata: list[dict[str, str]] | None = None) -> list[bytes]:
    """TRANSFORM messages (header v2 with ``metadata`` when given, else v1), one per row of matrices (N, 4, 4)."""
    m = np.asarray(matrices, float)
    contents = np.concatenate([np.swapaxes(m[:, :3, :3], 1, 2).reshape(-1, 9), m[:, :3, 3]], axis=1).astype(">f4")
    out = []
    for n, name in enumerate(names):
        body = contents[n].tobytes()
        version = 1
        if metadata is not None:
            version = 2
            keys = [(k.encode(), v.encode()) for k, v in metadata[n].items()]
            meta_header = struct.pack("> H", len(keys)) + b"".join(struct.pack("> H H I", len(k), 3, len(v))
                                                                   for k, v in keys)
            meta_body = b"".join(k + v for k, v in keys)
            body = _EXTENDED.pack(12, len(meta_header), len(meta_body), 0) + body + meta_header + meta_body
        seconds, fraction = _stamp(stamps[n])
        out.append(HEADER.pack(version, b"TRANSFORM", name.encode()[:20], seconds, fraction, len(body), CRC64(body))
                   + body)
    return out


class TrackingDataMessage(MessageBase):
    """TDATA: several named tool transforms in one message (OpenIGTLink v2; PLUS and Slicer read it).

    ``tools``: {name: 4x4 matrix}, translations in mm.
    """

    ELEMENT = struct.Struct("> 20s B B 12f")

    def __init__(self, tools: dict | None = None, timestamp=None, device_name=None):
        MessageBase.__init__(self, timestamp=timestamp, device_name=device_name)
        self._message_type = "TDATA"
        self.tools = dict(tools or {})
        self._valid_message = True

    def _pack_content(self):
        out = b""
        for name, m in self.tools.items():
            m = np.asarray(m, float)
            out += self.ELEMENT.pack(name.encode()[:20], 1, 0, *m[:3, :3].T.ravel(), *m[:3, 3])
        return out

    def _unpack_content(self, content):
        self.tools = {}
        for offset in range(0, len(content) - self.ELEMENT.size + 1, self.ELEMENT.size):
            name, _, _, *v = self.ELEMENT.unpack_from(content, offset)
            m = np.eye(4)
            m[:3, :3] = np.reshape(v[:9], (3, 3)).T
            m[:3, 3] = v[9:]
            self.tools[name.rstrip(b"\0").decode()] = m


class NDArrayMessage(MessageBase):
    """NDARRAY: an n-dimensional array (OpenIGTLink v2). ivc takes a (3, 3) array as a sensor's signal
    matrix (row = sensor coil, column = source coil)."""

    TYPES = {2: ">i1", 3: ">u1", 4: ">i2", 5: ">u2", 6: ">i4", 7: ">u4", 10: ">f4", 11: ">f8"}

    def __init__(self, array=None, timestamp=None, device_name=None):
        MessageBase.__init__(self, timestamp=timestamp, device_name=device_name)
        self._message_type = "NDARRAY"
        self.array = None if array is None else np.asarray(array, float)
        self._valid_message = True

    def _pack_content(self):
        a = np.asarray(self.array, ">f8")
        return struct.pack(f"> B B {a.ndim}H", 11, a.ndim, *a.shape) + a.tobytes()

    def _unpack_content(self, content):
        self.array = decode_ndarray(content)


message_type_to_class_constructor.setdefault("TDATA", TrackingDataMessage)
message_type_to_class_constructor.setdefault("NDARRAY", NDArrayMessage)
