"""Is a listening port free, and if not, who holds it.

The gateway checks its gRPC and line-protocol ports before it starts anything
(device processes included), so a port in use ends the start with one line:
``port 50051 (gateway.listen) is in use by python3 (pid 4242)``. The holder is
looked up the way ``ss -ltnp`` does it, without extra packages: the listening
socket's inode in ``/proc/net/tcp``/``tcp6``, then the process whose
``/proc/PID/fd`` links to that socket. Where that cannot be seen (another
user's process, no ``/proc``), the line says "another program".
"""

from __future__ import annotations

import contextlib
import errno
import os
import socket
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from aiohttp import web

    from gateway.connections import BoundedListener

#: ``st`` of a listening socket in /proc/net/tcp (include/net/tcp_states.h: TCP_LISTEN).
_TCP_LISTEN = "0A"


class PortInUse(Exception):
    """A port the gateway must listen on is taken; the message says which and by whom."""


def check_port_free(address: str, what: str) -> None:
    """Raise :class:`PortInUse` when ``address`` (``HOST:PORT``) cannot be bound now.

    Port 0 and unix-domain sockets are always free. Bound the way grpc and
    asyncio bind (``SO_REUSEADDR``), so a port only in TIME_WAIT counts as free.
    """
    if address.startswith("unix:"):
        return
    host, _, port_text = address.rpartition(":")
    port = int(port_text)
    if port == 0:
        return
    host = host.strip("[]") or "0.0.0.0"
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE:
                return  # not ours to judge (a host that is not local): the server's own bind reports it
            raise PortInUse(f"port {port} ({what}) is in use by {port_holder(port)}") from None


async def start_bounded(
    listener: BoundedListener, runner: web.AppRunner, host: str, port: int, what: str
) -> str:
    """Serve ``runner`` (set up, its server as ``listener``'s protocol factory) on ``host:port``
    through ``listener``; the address bound, ``HOST:PORT``.

    The runner is cleaned up when it cannot listen; a port in use is :class:`PortInUse` naming
    ``what`` (the option, ``http.listen``) and the holder.
    """
    try:
        bound = await listener.start(host, port)
    except OSError as exc:
        await runner.cleanup()
        if exc.errno != errno.EADDRINUSE:
            raise
        raise PortInUse(f"port {port} ({what}) is in use by {port_holder(port)}") from None
    shown = f"[{bound[0]}]" if ":" in bound[0] else bound[0]
    return f"{shown}:{bound[1]}"


def port_holder(port: int) -> str:
    """Who listens on TCP ``port``: ``"NAME (pid N)"``, or ``"another program"`` when it cannot be seen."""
    inodes = _listening_inodes(port)
    if inodes:
        for pid, name in _processes_holding(inodes):
            return f"{name} (pid {pid})"
    return "another program"


def _listening_inodes(port: int) -> set[str]:
    inodes: set[str] = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError):
            for line in Path(table).read_text().splitlines()[1:]:
                fields = line.split()
                if (
                    len(fields) > 9
                    and fields[3] == _TCP_LISTEN
                    and int(fields[1].rpartition(":")[2], 16) == port
                ):
                    inodes.add(fields[9])
    return inodes


def _processes_holding(inodes: set[str]) -> list[tuple[int, str]]:
    wanted = {f"socket:[{inode}]" for inode in inodes}
    found: list[tuple[int, str]] = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fds = os.listdir(entry / "fd")
        except OSError:
            continue  # gone, or another user's: not visible
        for fd in fds:
            with contextlib.suppress(OSError):
                if os.readlink(entry / "fd" / fd) in wanted:
                    name = (entry / "comm").read_text().strip() or "?"
                    found.append((int(entry.name), name))
                    break
    return found
