"""Many line-protocol devices in one process: the device side of part (h).

``python -m bench.device_farm --count 500 --first 0 --ports-file F`` serves
500 simulated robots, each a :class:`services.device.DeviceServer` of
its own on its own TCP port of 127.0.0.1, named ``m0`` … ``m499`` in their
greetings, and placed on a grid. It writes ``{"m0": PORT, ...}`` to ``F``,
then prints ``listening on 127.0.0.1:PORT`` (the first port) to stderr, and
serves until SIGTERM, SIGINT or end of file on stdin.

Before it writes the ports, each device is dialled once and must greet with
its own name: a port that the kernel handed out but that something else
intercepts (a container runtime's port forwarding, for one, rewrites every
local connection to its published port) would fail that device's
registration. Such a device is moved to another port.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import resource
import sys
from pathlib import Path

from bench.baseline import until_stopped
from services.apps.simulators import SimRobot
from services.device import DeviceServer
from services.kernel.core import LocalService

#: Each device serves the gateway's proxy and little else.
CONNECTIONS_PER_DEVICE = 4
#: File descriptors a process needs besides its sockets.
FD_SPARE = 256
#: Ports tried per device before the farm gives up, and seconds a device has to greet when dialled.
PORT_TRIES = 5
GREET_S = 5.0


def raise_fd_limit(needed: int) -> dict[str, int]:
    """Raise this process's soft limit on open files to ``needed`` (at most the hard limit).

    Child processes inherit it. Returns the limits before and after.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))
    after = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    return {"soft_before": int(soft), "soft": int(after), "hard": int(hard), "needed": int(needed)}


def device_name(number: int) -> str:
    """The name of device ``number`` in its greeting and in the registry."""
    return f"m{number}"


async def _greets(port: int, name: str) -> bool:
    """Whether a connection to 127.0.0.1:``port`` reaches device ``name`` (its greeting names it)."""
    try:
        async with asyncio.timeout(GREET_S):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            try:
                line = await reader.readline()
            finally:
                writer.close()
                with contextlib.suppress(OSError):
                    await writer.wait_closed()
    except (OSError, TimeoutError):
        return False
    return line.startswith(b"HELLO ") and f" name={name} ".encode() in line


async def _serve_reachable(backend: LocalService, name: str) -> tuple[DeviceServer, int]:
    """Serve ``backend`` as device ``name`` on a port of 127.0.0.1 that really reaches it."""
    for _ in range(PORT_TRIES):
        server = DeviceServer(backend, name=name, max_connections=CONNECTIONS_PER_DEVICE)
        _, port = await server.serve_tcp("127.0.0.1", 0)
        if await _greets(port, name):
            return server, port
        print(f"port {port} does not reach device {name} (intercepted?): trying another", file=sys.stderr)
        await server.aclose()
    raise RuntimeError(f"no port of 127.0.0.1 reached device {name} in {PORT_TRIES} tries")


async def serve(count: int, first: int, ports_file: Path) -> None:
    """Serve ``count`` devices, numbered from ``first``, until stopped."""
    backends: list[LocalService] = []
    servers: list[DeviceServer] = []
    ports: dict[str, int] = {}
    try:
        for number in range(first, first + count):
            backend = LocalService(SimRobot(start=(number % 100, number // 100), tick_hz=0.1))
            await backend.start()
            backends.append(backend)
            server, port = await _serve_reachable(backend, device_name(number))
            servers.append(server)
            ports[device_name(number)] = port
        await asyncio.to_thread(ports_file.write_text, json.dumps(ports))
        print(f"listening on 127.0.0.1:{next(iter(ports.values()))}", file=sys.stderr, flush=True)
        await until_stopped()
    finally:
        for server in servers:
            await server.aclose()
        for backend in backends:
            await backend.aclose()


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.device_farm --count N --first K --ports-file FILE``."""
    parser = argparse.ArgumentParser(prog="python -m bench.device_farm", description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, required=True, help="devices to serve")
    parser.add_argument("--first", type=int, default=0, help="number of the first device (default 0)")
    parser.add_argument("--ports-file", type=Path, required=True, help="where to write name → port as JSON")
    args = parser.parse_args(argv)
    if args.count < 1:
        parser.error("--count must be at least 1")
    logging.basicConfig(
        level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s"
    )
    limits = raise_fd_limit(2 * args.count + FD_SPARE)
    if limits["soft"] < 2 * args.count + FD_SPARE:
        print(f"error: open-file limit {limits['soft']} is too low for {args.count} devices", file=sys.stderr)
        return 1
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args.count, args.first, args.ports_file))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
