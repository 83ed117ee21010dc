"""CRC-8/SMBUS (polynomial 0x07, init 0, no reflection, no final XOR), see docs/device-spec.md §6.1.

CRC-8 rather than NMEA's XOR: an XOR misses two flipped bits in the same
position and swapped bytes, the usual damage of a noisy serial line; CRC-8
catches every burst of up to 8 bits and needs no table on the device.
"""

from __future__ import annotations


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _make_table()


def crc8(data: bytes | bytearray | memoryview) -> int:
    """The CRC-8 of ``data``; ``crc8(b"123456789") == 0xF4``."""
    crc = 0
    for byte in bytes(data):
        crc = _TABLE[crc ^ byte]
    return crc
