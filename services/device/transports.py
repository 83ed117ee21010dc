"""The byte streams a device server serves: serial ports and pseudo-terminals.

TCP needs nothing of its own (``asyncio.start_server`` / ``open_connection``);
a serial port is opened with pyserial-asyncio-fast, and a pty's master side
is a plain file descriptor wrapped in asyncio streams.
"""

from __future__ import annotations

import asyncio
import os

from services.device.session import READ_SIZE

__all__ = ["open_pty", "open_serial", "pipe_streams"]


async def open_serial(port: str, baudrate: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Asyncio streams on serial ``port``; OSError when it cannot be opened."""
    import serial
    import serial_asyncio_fast

    try:
        opened: tuple[asyncio.StreamReader, asyncio.StreamWriter]
        opened = await serial_asyncio_fast.open_serial_connection(
            url=port, baudrate=baudrate, limit=READ_SIZE
        )
    except (serial.SerialException, ValueError) as exc:
        raise OSError(f"cannot open serial port {port}: {exc}") from exc
    return opened


def open_pty() -> tuple[int, int, str]:
    """A new pseudo-terminal: (master fd, slave fd, the slave's path), the slave in raw mode.

    The slave is kept open by the caller so that the line stays up (and never
    echoes) while no client has it open, as a real serial line does when
    nobody listens.
    """
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)  # no echo, no line editing, until the client sets its own mode
    return master, slave, os.ttyname(slave)


async def pipe_streams(fd: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, asyncio.BaseTransport]:
    """Asyncio streams on a read/write file descriptor (on duplicates of it); the read transport, to close."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(limit=READ_SIZE)
    protocol = asyncio.StreamReaderProtocol(reader)
    read_transport, _ = await loop.connect_read_pipe(lambda: protocol, os.fdopen(os.dup(fd), "rb", 0))
    write_transport, write_protocol = await loop.connect_write_pipe(
        asyncio.streams.FlowControlMixin, os.fdopen(os.dup(fd), "wb", 0)
    )
    writer = asyncio.StreamWriter(write_transport, write_protocol, reader, loop)
    return reader, writer, read_transport
