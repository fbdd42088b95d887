"""OpenIGTLink messages as bytes (TRANSFORM, POLYDATA, STRING; header version 1) and a checked stream reader.

Layouts follow the OpenIGTLink protocol (all numbers big-endian): a 58-byte header (version,
type, device name, timestamp, body size, CRC-64/ECMA-182 of the body), then the body.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from liver_p2p_reg.errors import InputError, LiverP2PError

HEADER = struct.Struct(">H12s20sIIQQ")  # version, type, device, seconds, 2^-32 fraction, body size, CRC
HEADER_SIZE = HEADER.size  # 58
HEADER_VERSION = 1  # v1 headers are read by every Slicer and OpenIGTLink release
KNOWN_HEADER_VERSIONS = (1, 2)
# What a peer may send us: Slicer sends small messages (queries, its own transforms); a header
# announcing more than this is garbage, not a reason to buffer gigabytes.
MAX_PEER_BODY_BYTES = 16 * 1024 * 1024
POLYDATA_HEADER = struct.Struct(">10I")  # points, then (count, bytes) of vertices, lines, polygons, strips; attributes
ASCII, UTF8 = 3, 106  # IANA MIBenum of the STRING encodings
MAX_STRING_BYTES = 0xFFFF


class ProtocolError(LiverP2PError):
    """Bytes that are not a valid OpenIGTLink stream."""


def crc64(data: bytes | memoryview) -> int:
    """CRC-64/ECMA-182 (poly 0x42F0E1EBA9EA3693, init 0, not reflected), OpenIGTLink's checksum."""
    try:
        import fastcrc
    except ImportError:
        raise InputError("the Slicer link needs fastcrc: pip install 'liver_p2p_reg[slicer]'") from None
    return fastcrc.crc64.ecma_182(bytes(data))


def timestamp_fields(stamp_ns: int) -> tuple[int, int]:
    """(seconds, fraction of a second in units of 2^-32) of a stamp in nanoseconds."""
    seconds, nanoseconds = divmod(max(int(stamp_ns), 0), 1_000_000_000)
    return seconds & 0xFFFFFFFF, ((nanoseconds << 32) + 500_000_000) // 1_000_000_000  # rounded: 0.23 ns steps


def pack_message(type_name: str, device: str, body: bytes, stamp_ns: int) -> bytes:
    """Header + body of one message."""
    seconds, fraction = timestamp_fields(stamp_ns)
    header = HEADER.pack(
        HEADER_VERSION, type_name.encode("ascii"), device.encode("ascii"), seconds, fraction, len(body), crc64(body)
    )
    return header + body


def transform_body(matrix: np.ndarray) -> bytes:
    """TRANSFORM: the upper 3x4 of a 4x4 matrix, column by column (R11 R21 R31 R12 ... TX TY TZ), float32."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise InputError("TRANSFORM needs a finite 4x4 matrix")
    return np.ascontiguousarray(matrix[:3, :4].T, dtype=">f4").tobytes()


def string_body(text: str) -> bytes:
    """STRING: encoding, length, text (ASCII when it is, else UTF-8); cut to the format's 65535 bytes."""
    encoding = ASCII if text.isascii() else UTF8
    raw = text.encode("ascii" if encoding == ASCII else "utf-8")[:MAX_STRING_BYTES]
    if encoding == UTF8:
        raw = raw.decode("utf-8", errors="ignore").encode("utf-8")  # a cut must not split a character
    return struct.pack(">HH", encoding, len(raw)) + raw


def polydata_body(points: np.ndarray, triangles: np.ndarray | None = None) -> bytes:
    """POLYDATA: float32 points and, if given, triangles as POLYGONS cells (no vertices, lines, strips)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cells = b""
    n_cells = 0
    if triangles is not None and len(triangles):
        triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if triangles.min() < 0 or triangles.max() >= len(points):
            raise InputError("POLYDATA triangle refers to a point that does not exist")
        n_cells = len(triangles)
        cells = np.empty((n_cells, 4), dtype=">u4")
        cells[:, 0] = 3
        cells[:, 1:] = triangles
        cells = cells.tobytes()
    header = POLYDATA_HEADER.pack(len(points), 0, 0, 0, 0, n_cells, len(cells), 0, 0, 0)
    return header + points.astype(">f4").tobytes() + cells


@dataclass
class Message:
    """One message as read from a stream (body already CRC-checked)."""

    version: int
    type_name: str
    device: str
    stamp_ns: int
    body: bytes


def decode_transform(body: bytes) -> np.ndarray:
    """TRANSFORM body -> 4x4 float64 matrix."""
    if len(body) < 48:
        raise ProtocolError(f"TRANSFORM body has {len(body)} bytes (48 needed)")
    matrix = np.eye(4)
    matrix[:3, :4] = np.frombuffer(body[:48], dtype=">f4").reshape(4, 3).T
    return matrix


def decode_string(body: bytes) -> str:
    """STRING body -> text."""
    if len(body) < 4:
        raise ProtocolError("STRING body shorter than its 4-byte header")
    encoding, length = struct.unpack(">HH", body[:4])
    if len(body) < 4 + length:
        raise ProtocolError(f"STRING announces {length} bytes, has {len(body) - 4}")
    return body[4 : 4 + length].decode("ascii" if encoding == ASCII else "utf-8", errors="replace")


def decode_polydata(body: bytes) -> tuple[np.ndarray, list[np.ndarray]]:
    """POLYDATA body -> ((N, 3) float64 points, the POLYGONS cells as index arrays)."""
    if len(body) < POLYDATA_HEADER.size:
        raise ProtocolError("POLYDATA body shorter than its header")
    n_points, _, vert_bytes, _, line_bytes, n_polys, poly_bytes, _, strip_bytes, _ = POLYDATA_HEADER.unpack_from(body)
    start = POLYDATA_HEADER.size
    end = start + 12 * n_points
    if len(body) < end + vert_bytes + line_bytes + poly_bytes + strip_bytes:
        raise ProtocolError("POLYDATA body shorter than its header announces")
    points = np.frombuffer(body[start:end], dtype=">f4").reshape(-1, 3).astype(np.float64)
    start = end + vert_bytes + line_bytes
    words = np.frombuffer(body[start : start + poly_bytes], dtype=">u4").astype(np.int64)
    polygons, i = [], 0
    while i < len(words) and len(polygons) < n_polys:
        count = int(words[i])
        polygons.append(words[i + 1 : i + 1 + count])
        i += 1 + count
    return points, polygons


def _name(field: bytes, what: str, printable_only: bool) -> str:
    """A NUL-padded header name; anything else in it is garbage."""
    text, _, padding = field.partition(b"\0")
    if padding.strip(b"\0"):
        raise ProtocolError(f"{what} is not NUL-padded")
    if printable_only and not all(0x20 <= b < 0x7F for b in text):
        raise ProtocolError(f"{what} has non-printable bytes")
    if any(b < 0x20 or b == 0x7F for b in text):
        raise ProtocolError(f"{what} has control bytes")
    return text.decode("utf-8", errors="replace")


def parse_header(raw: bytes, max_body_bytes: int = MAX_PEER_BODY_BYTES) -> tuple[Message, int, int]:
    """(message without body, body size, CRC) of a 58-byte header; ProtocolError for garbage."""
    version, type_raw, device_raw, seconds, fraction, body_size, crc = HEADER.unpack(raw)
    if version not in KNOWN_HEADER_VERSIONS:
        raise ProtocolError(f"unknown header version {version}")
    type_name = _name(type_raw, "message type", printable_only=True)
    if not type_name:
        raise ProtocolError("empty message type")
    device = _name(device_raw, "device name", printable_only=False)
    if body_size > max_body_bytes:
        raise ProtocolError(f"body of {body_size} bytes announced (at most {max_body_bytes} accepted)")
    stamp_ns = seconds * 1_000_000_000 + ((fraction * 1_000_000_000 + (1 << 31)) >> 32)
    return Message(version, type_name, device, stamp_ns, b""), body_size, crc


class StreamReader:
    """Splits a byte stream into checked messages; raises ProtocolError at the first garbage."""

    def __init__(self, max_body_bytes: int = MAX_PEER_BODY_BYTES) -> None:
        self.max_body_bytes = max_body_bytes
        self._buffer = bytearray()
        self._pending: tuple[Message, int, int] | None = None  # parsed header waiting for its body

    def feed(self, data: bytes) -> list[Message]:
        self._buffer += data
        messages = []
        while True:
            if self._pending is None:
                if len(self._buffer) < HEADER_SIZE:
                    return messages
                self._pending = parse_header(bytes(self._buffer[:HEADER_SIZE]), self.max_body_bytes)
                del self._buffer[:HEADER_SIZE]
            message, body_size, crc = self._pending
            if len(self._buffer) < body_size:
                return messages
            body = bytes(self._buffer[:body_size])
            del self._buffer[:body_size]
            self._pending = None
            if crc64(body) != crc:
                raise ProtocolError(f"CRC mismatch in a {message.type_name} message")
            message.body = body
            messages.append(message)
