"""OpenIGTLink on a byte stream: framing, and the codec of the tracking messages both sides of ivc speak.

One codec for the live correction loop (:mod:`ivc.live`) and the collection client and server
(:mod:`ivc.collect.igtl`, :mod:`ivc.app.serve`); it imports nothing of ivc but its errors.
Message layouts: the OpenIGTLink protocol description v3.0 (openigtlink/OpenIGTLink,
``Documents/Protocol/header.md``, ``/transform.md``, ``/position.md``, ``/trackingdata.md``, ``/qtrackingdata.md``,
``/ndarray.md``); the v2/v3 extended header and metadata: the header page's "Version 2/3" sections.

pyigtl supplies the message classes and the CRC-64; its client and server threads are not used:
they poll with 10 ms socket timeouts and keep only the newest message per device, which would
add latency and drop frames at 240 Hz. :class:`Framer` splits a stream into whole messages,
checks each body's CRC-64, and resynchronises after garbage. The tracking messages of the hot
path (TRANSFORM, NDARRAY in; TRANSFORM out) are decoded and encoded here with NumPy: through
pyigtl's generic objects they cost more than the correction itself (benchmarks/bench_live.py).
"""

from __future__ import annotations

import logging
import math
import re
import selectors
import socket
import struct
import time
from collections import deque
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
#: a type name: characters 0-9, :;<=>?@, A-Z and _
_KIND = re.compile(rb"[0-9:;<=>?@A-Z_]+")
#: header type fields seen → type name ("" when not a valid one), and device fields → names: a stream repeats a few
_KINDS: dict[bytes, str] = {}
_NAMES: dict[bytes, str] = {}


def parse_url(url: str) -> tuple[str, int]:
    """``igtl://HOST:PORT`` (or ``HOST:PORT``) → (host, port)."""
    parsed = urlparse(url if "://" in url else f"igtl://{url}")
    if parsed.scheme != "igtl" or not parsed.hostname:
        raise InputError(f"expected igtl://HOST:PORT, got {url!r}")
    try:
        port = parsed.port
    except ValueError:  # not a number, or outside 0-65535
        raise InputError(f"{url!r}: the port must be a whole number from 1 to 65535") from None
    return parsed.hostname, port or DEFAULT_PORT


@dataclass
class Frame:
    """One whole message from the stream. ``payload``: the 4x4 matrix of a TRANSFORM (translation in the
    stream's unit), the array of an NDARRAY, else None (or always None from a framer made with
    ``decode=False``). ``body``: the message body as sent (v2/v3: extended header, content, metadata), for
    :func:`split_body`, of the small types of ``BODY_LIMITS`` only (empty for IMAGE, VIDEO, ...); ``version``
    its header version."""

    message_type: str
    device_name: str
    timestamp: float
    payload: np.ndarray | None
    body: bytes = b""
    version: int = 1


_EXTENDED = struct.Struct("> H H I I")
_TRANSFORM = np.dtype(">f4")


def _content(version: int, body: bytes) -> bytes:
    """The message content of a body: without the v2 extended header and metadata."""
    if version < 2:
        return body
    extended, meta_header, meta_body, _ = _EXTENDED.unpack_from(body)
    return body[extended:len(body) - meta_header - meta_body]


def split_body(version: int, body: bytes) -> tuple[bytes, bytes]:
    """(content, metadata) of a message body: the metadata part (its header and body) is empty for v1."""
    if version < 2:
        return body, b""
    extended, meta_header, meta_body, _ = _EXTENDED.unpack_from(body)
    end = len(body) - meta_header - meta_body
    return body[extended:end], body[end:]


def parse_metadata(raw: bytes) -> dict[str, str]:
    """The key/value metadata of a v2/v3 message (``raw``: the metadata header then body, as :func:`split_body`
    returns it); values decoded as UTF-8 (US-ASCII and UTF-8 are what PLUS and Slicer send)."""
    if len(raw) < 2:
        return {}
    (count,) = struct.unpack_from("> H", raw)
    entries = [struct.unpack_from("> H H I", raw, 2 + 8 * k) for k in range(count)]
    at = 2 + 8 * count
    out = {}
    for key_size, _, value_size in entries:
        key = raw[at:at + key_size].decode(errors="replace")
        at += key_size
        out[key] = raw[at:at + value_size].decode(errors="replace")
        at += value_size
    return out


def pack_metadata(metadata: dict[str, str]) -> tuple[bytes, bytes]:
    """(metadata header, metadata body) of ``metadata`` (values US-ASCII/UTF-8, IANA encoding 3)."""
    keys = [(k.encode(), v.encode()) for k, v in metadata.items()]
    header = struct.pack("> H", len(keys)) + b"".join(struct.pack("> H H I", len(k), 3, len(v)) for k, v in keys)
    return header, b"".join(k + v for k, v in keys)


def wrap_metadata(metadata: dict[str, str]) -> tuple[bytes, bytes]:
    """(what goes before, what goes after) a v2 message's content for ``metadata``: the extended header, and the
    metadata header and body. Compute it once for metadata that repeats (a tracker's statuses)."""
    meta_header, meta_body = pack_metadata(metadata)
    return _EXTENDED.pack(12, len(meta_header), len(meta_body), 0), meta_header + meta_body


def pack_message(kind: str, name: str, timestamp: float, content: bytes,
                 metadata: dict[str, str] | tuple[bytes, bytes] | None = None) -> bytes:
    """One whole message: header v2 with ``metadata`` when given (even empty; or as :func:`wrap_metadata` made
    it), else v1; ``timestamp`` in s."""
    wrap = metadata if metadata is None or isinstance(metadata, tuple) else wrap_metadata(metadata)
    return pack_messages(kind, [name], timestamp, [content], [wrap])[0]


def pack_messages(kind: str, names: list[str], timestamp: float, contents: list[bytes],
                  wraps: list[tuple[bytes, bytes] | None]) -> list[bytes]:
    """Messages of one type and time stamp (s), one per name: header v1 where ``wraps`` (from
    :func:`wrap_metadata`) is None, else v2 with that metadata. The hot path of a server."""
    seconds, fraction = _stamp(timestamp)
    kind_bytes = kind.encode()
    out = []
    for name, content, wrap in zip(names, contents, wraps, strict=True):
        body = content if wrap is None else wrap[0] + content + wrap[1]
        out.append(HEADER.pack(1 if wrap is None else 2, kind_bytes, name.encode()[:20], seconds, fraction,
                               len(body), CRC64(body)) + body)
    return out


def transform_contents(matrices: np.ndarray) -> np.ndarray:
    """The 48-byte TRANSFORM contents (N, 12) big-endian float32 of 4x4 matrices (N, 4, 4): the rotation
    column by column, then the translation."""
    m = np.asarray(matrices, float)
    return np.concatenate([np.swapaxes(m[:, :3, :3], 1, 2).reshape(-1, 9), m[:, :3, 3]], axis=1).astype(">f4")


def decode_transforms(contents: bytes) -> np.ndarray:
    """4x4 matrices (N, 4, 4) of N TRANSFORM contents joined end to end (48 bytes each), in one pass."""
    v = np.frombuffer(contents, _TRANSFORM).reshape(-1, 12).astype(float)
    m = np.zeros((len(v), 4, 4))
    m[:, :3, :3] = v[:, :9].reshape(-1, 3, 3).swapaxes(1, 2)
    m[:, :3, 3] = v[:, 9:]
    m[:, 3, 3] = 1.0
    return m


def decode_position(content: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion [w, x, y, z]) of a POSITION content: 12 bytes (position only: identity
    orientation), 24 (quaternion x, y, z; w = sqrt(1 - x^2 - y^2 - z^2)) or 28 (x, y, z, w)."""
    if len(content) not in (12, 24, 28):
        raise InputError(f"a POSITION message holds 12, 24 or 28 bytes, not {len(content)}")
    v = np.frombuffer(content, _TRANSFORM).astype(float)
    if len(v) == 3:
        return v, np.array([1.0, 0.0, 0.0, 0.0])
    xyz = v[3:6]
    w = v[6] if len(v) == 7 else math.sqrt(max(0.0, 1.0 - float(xyz @ xyz)))
    return v[:3], np.array([w, *xyz])


#: one TDATA element: name, type, reserved, the 3x4 matrix (rotation column by column, then translation)
TDATA_ELEMENT = np.dtype([("name", "S20"), ("type", "u1"), ("reserved", "u1"), ("matrix", ">f4", 12)])
#: one QTDATA element: name, type, reserved, position (x, y, z), quaternion (x, y, z, w)
QTDATA_ELEMENT = np.dtype([("name", "S20"), ("type", "u1"), ("reserved", "u1"), ("position", ">f4", 3),
                           ("quaternion", ">f4", 4)])


def decode_tdata(content: bytes) -> tuple[list[str], np.ndarray]:
    """(tool names, 4x4 matrices (N, 4, 4)) of a TDATA content (70-byte elements)."""
    if len(content) % TDATA_ELEMENT.itemsize:
        raise InputError(f"a TDATA message holds whole {TDATA_ELEMENT.itemsize}-byte elements")
    e = np.frombuffer(content, TDATA_ELEMENT)
    names = [n.rstrip(b"\0").decode(errors="replace") for n in e["name"]]
    return names, decode_transforms(e["matrix"].astype(">f4").tobytes())


def decode_qtdata(content: bytes) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(tool names, positions (N, 3), quaternions [w, x, y, z] (N, 4)) of a QTDATA content (50-byte elements)."""
    if len(content) % QTDATA_ELEMENT.itemsize:
        raise InputError(f"a QTDATA message holds whole {QTDATA_ELEMENT.itemsize}-byte elements")
    e = np.frombuffer(content, QTDATA_ELEMENT)
    names = [n.rstrip(b"\0").decode(errors="replace") for n in e["name"]]
    q = e["quaternion"].astype(float)
    return names, e["position"].astype(float), q[:, [3, 0, 1, 2]]


def encode_qtdata(names: list[str], positions: np.ndarray, quaternions: np.ndarray) -> bytes:
    """A QTDATA content: one element per tool (positions in the stream's unit, quaternions [w, x, y, z])."""
    e = np.zeros(len(names), QTDATA_ELEMENT)
    e["name"] = [n.encode()[:20] for n in names]
    e["type"] = 2  # a 6D instrument
    e["position"] = positions
    e["quaternion"] = np.asarray(quaternions, float)[:, [1, 2, 3, 0]]
    return e.tobytes()


def encode_position(position: np.ndarray, quaternion: np.ndarray) -> bytes:
    """A 28-byte POSITION content (position in the stream's unit, quaternion [w, x, y, z])."""
    q = np.asarray(quaternion, float)
    return np.concatenate([np.asarray(position, float), q[[1, 2, 3, 0]]]).astype(">f4").tobytes()


def ndarray_content(array: np.ndarray) -> bytes:
    """An NDARRAY content of ``array`` as 64-bit floats (scalar type 11)."""
    a = np.asarray(array, ">f8")
    return struct.pack(f"> B B {a.ndim}H", 11, a.ndim, *a.shape) + a.tobytes()


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
    whose content could not be decoded. With ``decode=False`` no content is decoded (the caller
    decodes :attr:`Frame.body` itself, for example many TRANSFORMs at once).
    """

    def __init__(self, timeout_s: float = BODY_TIMEOUT_S, decode: bool = True):
        self.buffer = bytearray()
        self.decode = decode
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
        version, raw, device, seconds, fraction, size, crc = HEADER.unpack_from(self.buffer, at)
        if version not in (1, 2, 3):
            return None
        kind = _KINDS.get(raw)
        if kind is None:
            kind = raw.rstrip(b"\0")
            kind = kind.decode() if _KIND.fullmatch(kind) is not None else ""  # 0-9, :;<=>?@, A-Z, _
            if len(_KINDS) < 4096:
                _KINDS[raw] = kind
        if not kind:
            return None
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
            small = kind in BODY_LIMITS  # a tracking message: its body is copied (a video frame's is not)
            body = b""
            if small and (at or self._partial is None):
                body = bytes(buf[at + HEADER_SIZE:end])
                running = CRC64(body)
            else:
                if at == 0 and self._partial is not None:  # the CRC of the body's start, computed as it arrived
                    running, done = self._partial
                else:
                    running, done = _CRC_START, 0
                with memoryview(buf) as view, view[at + HEADER_SIZE + done:end] as rest:
                    running = CRC64(rest, running)
                if small:
                    body = bytes(buf[at + HEADER_SIZE:end])
            self._partial = None
            if running != crc:
                skip = self._next_candidate(at + 1)
                self.garbage += skip - at
                at = skip
                continue
            payload = None
            decoder = _DECODERS.get(kind) if self.decode else None
            if decoder is not None:  # the small tracking messages: decoded from the body's copy
                try:
                    payload = decoder(_content(version, body))
                except (struct.error, ValueError):
                    self.bad += 1
            name = _NAMES.get(device)
            if name is None:
                if len(_NAMES) > 4096:
                    _NAMES.clear()
                name = _NAMES[device] = device.rstrip(b"\0").decode(errors="replace")
            out.append(Frame(kind, name, seconds + fraction / 2.0**32, payload, body, version))
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
    contents = transform_contents(matrices)
    return [pack_message("TRANSFORM", name, stamps[n], contents[n].tobytes(),
                         None if metadata is None else metadata[n]) for n, name in enumerate(names)]


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
        return ndarray_content(self.array)

    def _unpack_content(self, content):
        self.array = decode_ndarray(content)


message_type_to_class_constructor.setdefault("TDATA", TrackingDataMessage)
message_type_to_class_constructor.setdefault("NDARRAY", NDArrayMessage)


class _Client:
    """A downstream connection with its queue of whole messages."""

    def __init__(self, sock: socket.socket, address):
        self.sock, self.address = sock, address
        self.queue: deque[bytes] = deque()
        self.queued_bytes = 0
        self.pending = memoryview(b"")
        self.warned = False


class Downstream:
    """The clients of an OpenIGTLink server (ivc's live loop, ``ivc serve``), on the server's selector: each has a
    queue of whole messages, sent as the socket takes them. A client whose queue grows beyond
    ``max_queue_bytes`` loses its oldest messages (``dropped`` counts them), never anyone else's time; with
    ``lossless`` nothing is dropped and the server checks :attr:`backlogged` before making more. Clients may send
    commands: none is answered. Connections, departures and slow clients are logged on ``log``."""

    def __init__(self, selector: selectors.BaseSelector, log: logging.Logger, max_queue_bytes: int,
                 lossless: bool = False):
        self.selector, self.log = selector, log
        self.max_queue_bytes, self.lossless = int(max_queue_bytes), lossless
        self.clients: dict[int, _Client] = {}
        self.dropped = 0
        self.accepted = 0

    def accept(self, listener: socket.socket) -> None:
        try:
            sock, address = listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, address)
        self.clients[sock.fileno()] = client
        self.selector.register(sock, selectors.EVENT_READ, client)
        self.accepted += 1
        self.log.info("client %s:%d connected", *address[:2])

    def drop(self, client: _Client, reason: str) -> None:
        self.clients.pop(client.sock.fileno(), None)
        try:
            self.selector.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()
        self.log.info("client %s:%d %s", client.address[0], client.address[1], reason)

    def send(self, messages: list[bytes]) -> None:
        """Queue ``messages`` for every client and send what each socket takes now."""
        size = sum(len(m) for m in messages)
        for client in list(self.clients.values()):
            client.queue.extend(messages)
            client.queued_bytes += size
            while not self.lossless and client.queued_bytes > self.max_queue_bytes:
                client.queued_bytes -= len(client.queue.popleft())
                self.dropped += 1
                if not client.warned:
                    client.warned = True
                    self.log.warning("client %s:%d reads too slowly: dropping its oldest messages",
                                     *client.address[:2])
            self.flush(client)

    def flush(self, client: _Client) -> None:
        try:
            while True:
                if not client.pending:
                    if not client.queue:
                        break
                    batch = []
                    while client.queue and len(batch) < 4096:
                        batch.append(client.queue.popleft())
                    data = b"".join(batch)
                    client.queued_bytes -= len(data)
                    client.pending = memoryview(data)
                sent = client.sock.send(client.pending)
                client.pending = client.pending[sent:]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            self.drop(client, "disconnected")
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.pending or client.queue else 0)
        self.selector.modify(client.sock, events, client)

    def event(self, client: _Client, mask: int) -> None:
        """A selector event on ``client``'s socket."""
        if mask & selectors.EVENT_READ:
            try:
                data = client.sock.recv(1 << 16)
            except (BlockingIOError, InterruptedError):
                data = b"-"
            except OSError:
                data = b""
            if not data:
                self.drop(client, "disconnected")
                return
        if mask & selectors.EVENT_WRITE and client.sock.fileno() in self.clients:
            self.flush(client)

    @property
    def backlogged(self) -> bool:
        """Whether some client has more than ``max_queue_bytes`` waiting."""
        return any(c.queued_bytes + len(c.pending) > self.max_queue_bytes for c in self.clients.values())

    @property
    def idle(self) -> bool:
        """Whether every client has been sent all it was given."""
        return not any(c.queue or c.pending for c in self.clients.values())

    def close(self, listener: socket.socket | None = None) -> None:
        """Drop every client; with the server's ``listener``, also stop listening and close the selector (the
        server's whole shutdown, once the caller has unregistered its own sockets)."""
        for client in list(self.clients.values()):
            self.drop(client, "closed")
        if listener is None:
            return
        try:
            self.selector.unregister(listener)
        except (KeyError, ValueError):
            pass
        listener.close()
        self.selector.close()
