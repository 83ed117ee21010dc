"""Devices the gateway starts itself: Python stand-ins for microcontrollers, one process each.

A ``[[devices]]`` entry of the configuration (:class:`gateway.config.DeviceEntry`)
becomes a child process running this module::

    python -m gateway.devices --service sim-robot --name rover1 --tcp 127.0.0.1:0
    python -m gateway.devices --service sim-robot --name rover2 --pty

The child serves the service over the line protocol (``services.device_server``)
on raw TCP or on a pseudo-terminal, and prints one line saying where:
``listening on HOST:PORT`` or ``serial port /dev/pts/N``. The gateway reads that
line (bounded wait), then reaches the device through its ``tcp://`` or
``serial://`` proxy like any other device, and ends the child by its PID at
shutdown (SIGTERM, a bounded wait, then SIGKILL).

On a pseudo-terminal the child plays the microcontroller's end of the cable:
it serves the master side and reports the slave's path, which the gateway's
serial proxy opens with pyserial. The child keeps the slave open itself, in
raw mode, so that the line stays up (and never echoes) while the gateway has
it closed, as a real serial line does when nobody listens.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import re
import signal
import sys
import tty
from collections.abc import Mapping, Sequence
from typing import Any

from gateway.config import DeviceEntry
from services.errors import PropertyError, Unavailable

log = logging.getLogger(__name__)

#: Seconds a device process may take to say where it serves.
START_TIMEOUT = 10.0
#: Seconds a device process gets to end after SIGTERM before SIGKILL.
STOP_TIMEOUT = 3.0

_TCP_LINE = re.compile(r"listening on (\S+):(\d+)")
_PTY_LINE = re.compile(r"serial port (/\S+)")


class DeviceProcess:
    """A running device child process and the URL the gateway reaches it at."""

    def __init__(self, name: str, url: str, process: asyncio.subprocess.Process) -> None:
        self.name = name
        self.url = url
        self.process = process
        self._drain: asyncio.Task[None] | None = None
        if process.stdout is not None:
            self._drain = asyncio.create_task(_drain(name, process.stdout))

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self.process.pid

    async def aclose(self, wait_s: float = STOP_TIMEOUT) -> None:
        """End the child: SIGTERM, wait up to ``wait_s`` seconds, then SIGKILL. Idempotent."""
        await _terminate(self.process, wait_s)
        if self._drain is not None:
            self._drain.cancel()
            await asyncio.gather(self._drain, return_exceptions=True)
        log.info("device %s stopped (pid %d, exit %s)", self.name, self.pid, self.process.returncode)


async def _drain(name: str, stream: asyncio.StreamReader) -> None:
    # The child prints nothing more after its address; anything else is shown, never left to fill the pipe.
    while line := await stream.readline():
        log.info("device %s: %s", name, line.decode(errors="replace").rstrip())


async def _terminate(process: asyncio.subprocess.Process, wait_s: float) -> None:
    if process.returncode is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        process.send_signal(signal.SIGTERM)
    try:
        await asyncio.wait_for(process.wait(), wait_s)
    except TimeoutError:
        with contextlib.suppress(ProcessLookupError):
            process.kill()
        await asyncio.wait_for(process.wait(), wait_s)
    if process.stdin is not None:
        process.stdin.close()


def device_command(entry: DeviceEntry) -> list[str]:
    """The command line of the child process for ``entry``."""
    args = [sys.executable, "-m", "gateway.devices", "--service", entry.type, "--name", entry.name]
    args += ["--options", json.dumps(dict(entry.options)), "--exit-with-parent"]
    if entry.tcp:
        return [*args, "--tcp", entry.tcp]
    return [*args, "--pty"]


async def start_device(entry: DeviceEntry, *, wait_s: float = START_TIMEOUT) -> DeviceProcess:
    """Start the device process for ``entry`` and wait (at most ``wait_s`` s) until it says where it serves.

    Raises InvalidArgument for bad options and Unavailable when the process
    ends or stays silent; the process is ended in both cases.
    """
    from services.catalog import create

    create(entry.type, **entry.options)  # bad options fail here, with the catalog's message
    process = await asyncio.create_subprocess_exec(
        *device_command(entry),
        stdin=asyncio.subprocess.PIPE,  # the child ends when this pipe closes, even if the gateway is killed
        stdout=asyncio.subprocess.PIPE,
    )
    try:
        async with asyncio.timeout(wait_s):
            first = (await process.stdout.readline()).decode(errors="replace").strip()  # type: ignore[union-attr]
    except TimeoutError:
        await _terminate(process, STOP_TIMEOUT)
        raise Unavailable(f"device {entry.name}: did not say where it serves within {wait_s:g} s") from None
    except BaseException:
        await _terminate(process, STOP_TIMEOUT)
        raise
    if m := _TCP_LINE.fullmatch(first):
        url = f"tcp://{m.group(1)}:{m.group(2)}"
    elif m := _PTY_LINE.fullmatch(first):
        url = f"serial://{m.group(1)}?baudrate={entry.baudrate}"
    else:
        await _terminate(process, STOP_TIMEOUT)
        raise Unavailable(
            f"device {entry.name}: the device process did not start (exit {process.returncode},"
            f" said {first!r}; its errors are in the log above)"
        )
    device = DeviceProcess(entry.name, url, process)
    log.info("device %s started (pid %d) at %s", entry.name, device.pid, url)
    return device


# -- the child process --------------------------------------------------------


async def _pty_streams(
    master: int,
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, asyncio.BaseTransport]:
    """Asyncio streams on a pty master (its own fds); the read transport, to close it."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(limit=65536)
    protocol = asyncio.StreamReaderProtocol(reader)
    read_transport, _ = await loop.connect_read_pipe(lambda: protocol, os.fdopen(os.dup(master), "rb", 0))
    write_transport, write_protocol = await loop.connect_write_pipe(
        asyncio.streams.FlowControlMixin, os.fdopen(os.dup(master), "wb", 0)
    )
    writer = asyncio.StreamWriter(write_transport, write_protocol, reader, loop)
    return reader, writer, read_transport


async def _serve_pty(server: Any, master: int, path: str) -> None:
    """Serve the master side of the pty until cancelled (a session that ends is started again)."""
    while True:
        reader, writer, read_transport = await _pty_streams(master)
        try:
            await server.serve_stream(reader, writer, peer=path)
        finally:
            read_transport.close()
            writer.close()
        log.info("%s: session ended; serving the line again", path)
        await asyncio.sleep(0.5)


async def _watch_parent(stop: asyncio.Event) -> None:
    """Set ``stop`` when stdin reaches its end: the gateway that started this process is gone."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    transport, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    try:
        while await reader.read(4096):
            pass
    finally:
        transport.close()
        stop.set()


async def serve_child(args: argparse.Namespace) -> None:
    """The child process: serve the device until SIGTERM/SIGINT (or, with --exit-with-parent, stdin's end)."""
    from services.catalog import create
    from services.core import LocalService
    from services.device_server import DeviceServer

    backend = LocalService(create(args.service, **args.options))
    await backend.start()
    server = DeviceServer(backend, name=args.name or args.service)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    tasks: list[asyncio.Task[None]] = []
    if args.exit_with_parent:
        tasks.append(asyncio.create_task(_watch_parent(stop)))
    master = slave = -1
    try:
        if args.tcp:
            host, port = await server.serve_tcp(*args.tcp)
            print(f"listening on {host}:{port}", flush=True)
        else:
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line editing, until the gateway's pyserial sets its own mode
            path = os.ttyname(slave)
            tasks.append(asyncio.create_task(_serve_pty(server, master, path)))
            print(f"serial port {path}", flush=True)
        await stop.wait()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await server.aclose()
        await backend.aclose()
        for fd in (master, slave):
            if fd >= 0:
                os.close(fd)


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, e.g. 127.0.0.1:7001, not {text!r}")
    return host.strip("[]") or "127.0.0.1", int(port)


def _options(text: str) -> Mapping[str, Any]:
    try:
        value = json.loads(text)
    except ValueError:
        value = None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object like '{{\"speed\": 0.5}}', not {text!r}")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m gateway.devices``: one device process; the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m gateway.devices",
        description="Serve one service over the line protocol on TCP or on a new pseudo-terminal.",
    )
    parser.add_argument("--service", required=True, help="kind of service, e.g. sim-robot")
    parser.add_argument("--name", help="name in the greeting (default: the service kind)")
    parser.add_argument("--options", type=_options, default={}, help="service options as a JSON object")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", type=_host_port, metavar="HOST:PORT", help="listen on TCP (port 0: pick one)")
    where.add_argument(
        "--pty", action="store_true", help="create a pseudo-terminal and serve its master side"
    )
    parser.add_argument("--exit-with-parent", action="store_true", help="stop when stdin reaches its end")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=str(args.log_level).upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        asyncio.run(serve_child(args))
    except PropertyError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


__all__ = ["START_TIMEOUT", "STOP_TIMEOUT", "DeviceProcess", "device_command", "main", "start_device"]

if __name__ == "__main__":
    raise SystemExit(main())
