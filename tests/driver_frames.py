"""Reference frame builders for the driver tests, independent of the code under test.

A bitwise CRC-16/ARC written from the protocol facts (reflected polynomial 0xA001, init 0,
no final XOR), used to build command and reply frames for scripted exchanges.
"""

from __future__ import annotations

import struct


def ref_crc(data: bytes) -> int:
    """CRC-16/ARC, bit by bit: reflected polynomial 0xA001, init 0, no final XOR."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def cmd(body: bytes) -> bytes:
    """A command frame: body + CRC, low byte first."""
    c = ref_crc(body)
    return body + bytes([c & 0xFF, c >> 8])


def rep(prefix: bytes, data: bytes = b"") -> bytes:
    """A reply frame: payload + CRC + CR LF."""
    return cmd(prefix + data) + b"\r\n"


def i16(v: int) -> bytes:
    """Big-endian signed 16-bit."""
    return struct.pack(">h", v)
