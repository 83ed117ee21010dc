"""Start line-protocol devices as real processes, talk to them with raw sockets and ptys, and
proxy them with the gateway's TCP proxy."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator, Mapping
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path

from gateway.proxies import TcpProxy, open_tcp_backend

ROOT = Path(__file__).resolve().parents[2]


@contextmanager
def device_process(
    *args: str, env: dict[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """Run ``python -m services.device ARGS``; yield it and its first line of output."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.device", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline().strip()
        assert first, f"device exited with {proc.wait(5)}"
        yield proc, first
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@contextmanager
def tcp_device(*args: str, env: dict[str, str] | None = None) -> Iterator[tuple[str, int]]:
    """A device process on a free TCP port of 127.0.0.1; yields (host, port)."""
    with device_process(*args, "--tcp", "127.0.0.1:0", env=env) as (_, first):
        match = re.fullmatch(r"listening on (.+):(\d+)", first)
        assert match, first
        yield match.group(1), int(match.group(2))


@asynccontextmanager
async def started_tcp_proxy(url: str, options: Mapping[str, object]) -> AsyncIterator[TcpProxy]:
    """The gateway's proxy for the device at ``url`` (``tcp://HOST:PORT``), started; closed at the end."""
    proxy = open_tcp_backend("dev", url, options)
    assert isinstance(proxy, TcpProxy)
    await proxy.start()
    try:
        yield proxy
    finally:
        await proxy.aclose()


@contextmanager
def pty_pair() -> Iterator[tuple[int, str]]:
    """A pseudo-terminal: (master fd, slave path).

    The test keeps the slave open too: while no process has it open, reading
    the master fails with EIO.
    """
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        yield master, path
    finally:
        os.close(master)
        os.close(slave)


class LineClient:
    """A raw line-protocol client over asyncio streams (TCP or a pty master)."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        read_transport: asyncio.BaseTransport | None = None,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self._read_transport = read_transport

    @classmethod
    async def tcp(cls, host: str, port: int) -> LineClient:
        reader, writer = await asyncio.open_connection(host, port)
        return cls(reader, writer)

    async def send(self, *lines: str | bytes) -> None:
        for line in lines:
            self.writer.write(line if isinstance(line, bytes) else line.encode() + b"\n")
        await self.writer.drain()

    async def line(self, wait: float = 5.0) -> str:
        data = await asyncio.wait_for(self.reader.readline(), wait)
        assert data.endswith(b"\n"), f"connection closed: {data!r}"
        return data.decode().rstrip("\n")

    async def lines(self, count: int, wait: float = 5.0) -> list[str]:
        return [await self.line(wait) for _ in range(count)]

    async def until(self, prefix: str, wait: float = 5.0) -> tuple[str, list[str]]:
        """Read until a line starting with ``prefix``; return it and the lines before it."""
        before = []
        deadline = time.monotonic() + wait
        while True:
            line = await self.line(max(0.01, deadline - time.monotonic()))
            if line.startswith(prefix):
                return line, before
            before.append(line)

    async def replies(self, count: int, wait: float = 5.0) -> list[str]:
        """The next ``count`` lines that are not EVENT lines."""
        out: list[str] = []
        while len(out) < count:
            line = await self.line(wait)
            if not line.startswith("EVENT "):
                out.append(line)
        return out

    async def close(self) -> None:
        self.writer.close()
        if self._read_transport is not None:  # a pty: two pipe transports, nothing to wait for
            self._read_transport.close()
            return
        with contextlib.suppress(ConnectionError, OSError):
            await self.writer.wait_closed()


async def pty_client(master: int) -> LineClient:
    """A LineClient on the master side of a pty."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    protocol = asyncio.StreamReaderProtocol(reader)
    fd = os.dup(master)
    read_file = os.fdopen(fd, "rb", buffering=0)
    read_transport, _ = await loop.connect_read_pipe(lambda: protocol, read_file)
    write_fd = os.dup(master)
    write_file = os.fdopen(write_fd, "wb", buffering=0)
    transport, wprotocol = await loop.connect_write_pipe(asyncio.streams.FlowControlMixin, write_file)
    writer = asyncio.StreamWriter(transport, wprotocol, reader, loop)
    return LineClient(reader, writer, read_transport)
