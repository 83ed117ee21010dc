"""The byte streams a device server serves: serial ports and pseudo-terminals.

TCP needs nothing of its own (``asyncio.start_server`` / ``open_connection``);
a serial port is opened with pyserial-asyncio-fast, and a pty's master side
is a plain file descriptor wrapped in asyncio streams.
"""

from __future__ import annotations

import asyncio
import logging
import os

from services.device.session import READ_SIZE

__all__ = ["open_pty", "open_serial", "pipe_streams", "serial_streams"]

_log = logging.getLogger(__name__)


async def open_serial(port: str, baudrate: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Asyncio streams on serial ``port``; OSError when it cannot be opened."""
    import serial

    try:
        return await serial_streams(port, baudrate, READ_SIZE)
    except (serial.SerialException, ValueError) as exc:
        raise OSError(f"cannot open serial port {port}: {exc}") from exc


async def serial_streams(
    port: str, baudrate: int, limit: int
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Asyncio streams on serial ``port`` (what ``serial_asyncio_fast.open_serial_connection``
    makes, on the transport below); pyserial's SerialException or ValueError when it cannot be
    opened."""
    import serial
    import serial_asyncio_fast

    class SerialTransport(serial_asyncio_fast.SerialTransport):  # type: ignore[misc]
        """serial_asyncio_fast 0.16's transport, with its writer let go once the buffer is empty:
        its ``_write_ready`` keeps the writer registered after writing everything, so the next
        "ready" finds nothing to write and fails an assertion in a loop callback (a traceback in
        the log for every one, after any write the port took in more than one go)."""

        def _write_ready(self) -> None:
            if self._write_buffer:
                super()._write_ready()
            if not self._write_buffer:
                self._remove_writer()

        def _fatal_error(self, exc: BaseException, message: str = "Fatal error on serial transport") -> None:
            # A line that went away (the other end of a pty closed, a USB adapter unplugged: EIO)
            # is a device leaving, which the connection above reports and reconnects from: one
            # line, not the loop's traceback. Anything else keeps the loop's report.
            if isinstance(exc, OSError):  # pyserial's SerialException is one
                _log.info("serial line %s closed: %s", port, exc)
                self._abort(exc)
                return
            super()._fatal_error(exc, message)

    loop = asyncio.get_running_loop()
    line = await loop.run_in_executor(None, lambda: serial.serial_for_url(port, baudrate=baudrate))
    reader = asyncio.StreamReader(limit=limit)
    protocol = asyncio.StreamReaderProtocol(reader)
    transport = SerialTransport(loop, protocol, line)
    return reader, asyncio.StreamWriter(transport, protocol, reader, loop)


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
