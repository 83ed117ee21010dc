"""The device command: ``python -m services.device`` and ``psgateway device``.

::

    python -m services.device --service sim-robot --tcp 127.0.0.1:7001
    python -m services.device --service sim-sensor --serial /dev/pts/3 --baud 115200
    python -m services.device --service sim-robot --name scout4 --connect 127.0.0.1:7100
    python -m services.device --service sim-robot --name rover2 --pty

With ``--connect`` the device dials out to a gateway's line listener and
greets; the gateway registers it under its name (docs/line-protocol.md §5).
With ``--pty`` it creates a pseudo-terminal, plays the device's end of the
cable on its master side and prints the other end's path (``serial port
/dev/pts/N``) for a ``serial://`` client to open. With ``--exit-with-parent``
it stops when its stdin reaches its end: the gateway starts its ``[[devices]]``
this way (``gateway.devices``), so they end with it even when it is killed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import signal
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from services.device.server import DIAL_KEEPALIVE, DeviceServer
from services.device.session import KEEPALIVE_TIMEOUT
from services.kernel.backend import Backend
from services.kernel.errors import PropertyError
from services.kernel.line_protocol import MAX_INFLIGHT, MAX_LINE, MAX_RXBUF, MIN_MAX_LINE, MIN_RXBUF

__all__ = ["DESCRIPTION", "add_arguments", "bounded_int", "main", "run", "serve"]

DESCRIPTION = "Serve any Property Service over the line protocol, on a TCP port or a serial port."
#: The longest ``--max-line``: a line with the base64 of the largest value one gRPC message
#: carries (4 MiB) fits, as the proxies' ``maxline`` option allows.
MAX_LINE_LIMIT = 8 * 1024 * 1024


async def _watch_stdin(stop: asyncio.Event) -> None:
    """Set ``stop`` when stdin reaches its end: the process that started this one is gone."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    transport, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    try:
        while await reader.read(4096):
            pass
    finally:
        transport.close()
        stop.set()


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, e.g. 127.0.0.1:7001, not {text!r}")
    return host.strip("[]") or "127.0.0.1", int(port)


def _option(text: str) -> tuple[str, Any]:
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, not {text!r}")
    try:
        return key, json.loads(raw)
    except ValueError:
        return key, raw


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the device command (shared by ``psgateway device`` and ``python -m``)."""
    parser.add_argument(
        "--service", required=True, help="kind of service to serve, e.g. sim-robot, sim-sensor"
    )
    parser.add_argument("--name", help="name in the greeting (default: the service kind)")
    parser.add_argument(
        "--option",
        action="append",
        type=_option,
        default=[],
        metavar="KEY=VALUE",
        help="service option; VALUE is JSON when it parses as JSON, else text (repeatable)",
    )
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", type=_host_port, metavar="HOST:PORT", help="listen on TCP (port 0: pick one)")
    where.add_argument(
        "--connect",
        type=_host_port,
        metavar="HOST:PORT",
        help="dial a gateway's line listener and greet: it registers the device under --name",
    )
    where.add_argument(
        "--serial", metavar="PORT", help="serve on a serial port, e.g. /dev/ttyUSB0 or /dev/pts/3"
    )
    where.add_argument(
        "--pty",
        action="store_true",
        help="create a pseudo-terminal, serve its master side and print the serial port to open"
        " ('serial port /dev/pts/N')",
    )
    parser.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    parser.add_argument("--no-push", action="store_true", help="act as a device that cannot push events")
    parser.add_argument("--checksum", action="store_true", help="send a CRC-8 checksum on every line")
    parser.add_argument(
        "--max-line",
        type=bounded_int("max-line", MIN_MAX_LINE, MAX_LINE_LIMIT),
        default=MAX_LINE,
        help=f"longest line accepted, stated as maxline= (default {MAX_LINE}); lines sent may be as "
        "long when it is larger: raise it (and the proxy's maxline) for large binary values "
        "(docs/line-protocol.md §11)",
    )
    parser.add_argument(
        "--inflight",
        type=bounded_int("inflight", 1, MAX_INFLIGHT),
        help="state inflight=N in the greeting: requests taken at once (docs/device-spec.md §5)",
    )
    parser.add_argument(
        "--rxbuf",
        type=bounded_int("rxbuf", MIN_RXBUF, MAX_RXBUF),
        help="state rxbuf=N in the greeting: bytes of unanswered requests the device holds",
    )
    parser.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop when stdin reaches its end (a device process that must end with the one that started it)",
    )
    parser.add_argument(
        "--secret-file",
        help="a file holding the secret the greeting carries (secret=...) when dialling a gateway that "
        "configures this device",
    )
    parser.add_argument(
        "--keepalive",
        type=_seconds("keepalive", 0.0, 3600.0),
        default=DIAL_KEEPALIVE,
        help="with --connect: PING a gateway silent this many seconds, and dial the next one when it "
        "does not answer within --keepalive-timeout (a frozen gateway; "
        f"default {DIAL_KEEPALIVE:g}; 0: never)",
    )
    parser.add_argument(
        "--keepalive-timeout",
        type=_seconds("keepalive-timeout", 0.01, 600.0),
        default=KEEPALIVE_TIMEOUT,
        help=f"seconds the gateway has to answer the keep-alive PING (default {KEEPALIVE_TIMEOUT:g})",
    )
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")


def _seconds(what: str, low: float, high: float) -> Callable[[str], float]:
    """An argparse type: seconds from ``low`` to ``high`` (0 allowed where ``low`` is 0)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number of seconds, not {text!r}") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"{what} must be from {low:g} to {high:g} seconds")
        return value

    return parse


def bounded_int(what: str, low: int, high: int) -> Callable[[str], int]:
    """An argparse type: an integer from ``low`` to ``high`` (the greeting's bounds, device-spec §5)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, not {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{what} must be from {low} to {high}")
        return value

    return parse


def _make_backend(kind: str, options: Mapping[str, Any]) -> Backend:
    from services.apps.catalog import build
    from services.kernel.core import serve

    return serve(build(kind, options))


def _read_secret(path: str) -> str:
    from pathlib import Path

    return Path(path).read_text(encoding="utf-8").strip()


async def serve(args: argparse.Namespace) -> None:
    """Run the device described by parsed ``args`` until SIGINT/SIGTERM (or stdin's end, if asked)."""
    backend = _make_backend(args.service, dict(args.option))
    await backend.start()
    server = DeviceServer(
        backend,
        name=args.name or args.service,
        push=not args.no_push,
        checksum=args.checksum,
        max_line=args.max_line,
        inflight=getattr(args, "inflight", None),
        rxbuf=getattr(args, "rxbuf", None),
        secret=_read_secret(args.secret_file) if getattr(args, "secret_file", None) else "",
        keepalive=getattr(args, "keepalive", DIAL_KEEPALIVE),
        keepalive_timeout=getattr(args, "keepalive_timeout", KEEPALIVE_TIMEOUT),
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    tasks: list[asyncio.Task[None]] = []
    if getattr(args, "exit_with_parent", False):
        tasks.append(asyncio.create_task(_watch_stdin(stop)))
    try:
        if args.tcp:
            host, port = await server.serve_tcp(*args.tcp)
            print(f"listening on {host}:{port}", flush=True)
        elif getattr(args, "connect", None):
            host, port = args.connect
            tasks.append(asyncio.create_task(server.dial(host, port)))
            print(f"connecting to {host}:{port}", flush=True)
        elif getattr(args, "pty", False):
            print(f"serial port {server.serve_pty()}", flush=True)
        else:
            await server.serve_serial(args.serial, args.baud)
            print(f"serving on {args.serial}", flush=True)
        await stop.wait()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await server.aclose()
        await backend.aclose()


def run(args: argparse.Namespace) -> int:
    """Run the device command; return the process exit status."""
    logging.basicConfig(
        level=str(args.log_level).upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        asyncio.run(serve(args))
    except PropertyError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m services.device``."""
    parser = argparse.ArgumentParser(
        prog="python -m services.device",
        description=DESCRIPTION,
    )
    add_arguments(parser)
    return run(parser.parse_args(argv))
