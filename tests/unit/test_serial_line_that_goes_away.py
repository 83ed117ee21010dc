"""A serial line whose other end goes away while the gateway writes to it: the transport ends
with one log line, never the event loop's traceback (the test suite fails a gateway process that
logs one)."""

from __future__ import annotations

import asyncio
import logging
import os

import pytest

from services.device.transports import open_pty, serial_streams


async def test_a_write_to_a_line_whose_other_end_closed_ends_it_with_one_quiet_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    master, slave, path = open_pty()
    os.close(slave)
    _reader, writer = await serial_streams(path, 115200, 1024)
    os.close(master)  # the device's end goes: writes now fail with EIO
    caplog.set_level(logging.DEBUG)
    for _ in range(20):
        writer.write(b"GET temp\n" * 200)
        await asyncio.sleep(0.01)
        if writer.transport.is_closing():
            break
    assert writer.transport.is_closing(), "the write error ended the transport"
    assert not any(record.exc_info for record in caplog.records), [r.getMessage() for r in caplog.records]
    assert not any(record.levelno >= logging.ERROR for record in caplog.records)
    assert any(
        "closed" in record.getMessage() for record in caplog.records if record.name.startswith("services")
    )
    writer.close()
