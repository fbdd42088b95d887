"""An MCAP file's framing (magic, footer, record lengths) checked before a reader trusts it: one line, not a crash."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from liver_p2p_reg.errors import InputError

MCAP_MAGIC = b"\x89MCAP0\r\n"
_FOOTER = 0x02  # MCAP opcode of the Footer record (29 bytes with its head), just before the closing magic
_FOOTER_BYTES = 29  # opcode, length, summary_start, summary_offset_start, summary_crc


def starts_as_mcap(path: Path) -> bool:
    """Whether a file begins with the MCAP magic (False when it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def mcap_closed(fh: BinaryIO, size: int) -> bool:
    """Whether an MCAP file ends with its Footer and magic (closed by its writer, not cut short)."""
    if size < 8 + _FOOTER_BYTES + 8:
        return False
    fh.seek(size - 8 - _FOOTER_BYTES)
    tail = fh.read(_FOOTER_BYTES + 8)
    return tail[0] == _FOOTER and tail[-8:] == MCAP_MAGIC


def summary_start(fh: BinaryIO, size: int) -> int:
    """Where a closed MCAP file's summary section begins (its Footer's summary_start; 0: no summary)."""
    fh.seek(size - 8 - _FOOTER_BYTES + 9)
    return struct.unpack("<Q", fh.read(8))[0]


def mcap_record_heads(fh: BinaryIO, start: int, size: int) -> Iterator[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level MCAP records from `start` on, without reading their bodies.

    Lengths are not checked: the caller decides what a record running past the end means.
    """
    offset = start
    while offset + 9 <= size:
        fh.seek(offset)
        opcode, length = struct.unpack("<BQ", fh.read(9))
        yield offset, opcode, length
        offset += 9 + length


def check_bare_mcap(path: Path) -> None:
    """InputError (one line) for a .mcap file that rosbags would report as "File end magic is invalid", crash on or
    try to allocate terabytes for: one without its footer, or one with a record whose length runs past its end."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        if fh.read(8) != MCAP_MAGIC:
            return  # no MCAP file at all: rosbags says so
        if not mcap_closed(fh, size):
            hint = ""
            if looks_like_recording(path):
                hint = (
                    f"; `liver-p2p replay {path}` reads a flight recording up to its last complete registration, "
                    "bag info and bag play need a closed file"
                )
            raise InputError(
                f"cannot read bag {path}: it ends without its footer (cut short, or its writer was killed){hint}"
            )
        for offset, opcode, length in mcap_record_heads(fh, 8, size - 8):
            if offset + 9 + length > size - 8:
                raise InputError(
                    f"cannot read bag {path}: the record at byte {offset} claims {length} bytes, "
                    f"past the end of the file ({size} bytes): damaged"
                )
            if opcode == _FOOTER:
                return


def looks_like_recording(path: Path) -> bool:
    """Whether a .mcap file is a flight recording, a damaged one or one of another format included."""
    from liver_p2p_reg.bags.flight_read import is_recording

    try:
        return is_recording(path)
    except InputError:  # its head is damaged, or it is of another format: a recording all the same
        return True
