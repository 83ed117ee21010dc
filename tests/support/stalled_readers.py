"""Readers that never read: raw sockets with a tiny receive buffer that open a live image
(``/stream``), an event stream (SSE) or a gRPC Listen on a binary property, then read nothing.

What a slow or hostile client does to a gateway that writes binary values to it. Each reader is a
plain blocking socket; :func:`open_readers` opens them, the caller closes them with
:func:`close_readers`. The gRPC reader speaks just enough HTTP/2 by hand (the connection preface,
SETTINGS, one HEADERS frame with literal HPACK fields and one DATA frame) to start a Listen, and
announces the largest flow-control windows, so that only the socket holds the gateway back.

Run as a module to measure the full-size attack against a fresh gateway process (its RSS before,
while the readers stall, and after they close)::

    PYTHONPATH=$PWD:$PWD/tests python -m support.stalled_readers --kind sse --readers 60 --size 3900000
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import struct
import tempfile
import time
from pathlib import Path

import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: The receive buffer each reader asks for; the kernel makes it at least a few KiB.
RECEIVE_BUFFER = 4096
KINDS = ("stream", "sse", "grpc", "session")

_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
_SETTINGS, _HEADERS, _DATA, _WINDOW_UPDATE = 0x4, 0x1, 0x0, 0x8
_END_STREAM, _END_HEADERS, _ACK = 0x1, 0x4, 0x1
_INITIAL_WINDOW_SIZE = 0x4
_MAX_WINDOW = 2**31 - 1


def _frame(kind: int, flags: int, stream: int, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload))[1:] + bytes((kind, flags)) + struct.pack(">I", stream) + payload


def _literal(name: str, value: str) -> bytes:
    # HPACK "literal header field without indexing, new name", no Huffman (RFC 7541 §6.2.2);
    # every name and value here is shorter than 127 bytes.
    return b"\x00" + bytes((len(name),)) + name.encode() + bytes((len(value),)) + value.encode()


def grpc_listen_bytes(authority: str, service: str, path: str, *, session: bool = False) -> bytes:
    """What a gRPC client sends to start a Listen of ``service``/``path`` (and nothing after); with
    ``session``, a Session whose one request is that Listen, left open (a half-close ends it)."""
    headers = b"".join(
        _literal(name, value)
        for name, value in (
            (":method", "POST"),
            (":scheme", "http"),
            (":path", f"/propertyservice.v1.PropertyService/{'Session' if session else 'Listen'}"),
            (":authority", authority),
            ("content-type", "application/grpc"),
            ("te", "trailers"),
        )
    )
    listen = pb.ListenRequest(service=service, property=path)
    if session:
        request = pb.SessionRequest(requests=[pb.Request(id=1, listen=listen)]).SerializeToString()
    else:
        request = listen.SerializeToString()
    message = b"\x00" + struct.pack(">I", len(request)) + request
    settings = struct.pack(">HI", _INITIAL_WINDOW_SIZE, _MAX_WINDOW)
    return b"".join(
        (
            _PREFACE,
            _frame(_SETTINGS, 0, 0, settings),
            _frame(_WINDOW_UPDATE, 0, 0, struct.pack(">I", _MAX_WINDOW - 65535)),
            _frame(_SETTINGS, _ACK, 0, b""),  # the gateway's SETTINGS, acknowledged unread
            _frame(_HEADERS, _END_HEADERS, 1, headers),
            _frame(_DATA, 0 if session else _END_STREAM, 1, message),
        )
    )


def http_get_bytes(authority: str, target: str) -> bytes:
    return f"GET {target} HTTP/1.1\r\nHost: {authority}\r\n\r\n".encode()


def websocket_text_frame(text: str) -> bytes:
    """One client-to-server WebSocket text frame (RFC 6455 5.2), masked as a client's must be, with
    the all-zero mask: the payload goes as it is."""
    payload = text.encode()
    length = len(payload)
    if length < 126:
        head = bytes([0x81, 0x80 | length])
    elif length < 65536:
        head = bytes([0x81, 0x80 | 126]) + length.to_bytes(2, "big")
    else:
        head = bytes([0x81, 0x80 | 127]) + length.to_bytes(8, "big")
    return head + bytes(4) + payload


def rosbridge_subscribe_bytes(authority: str, topic: str) -> bytes:
    """A WebSocket upgrade to ``/rosbridge`` and, right behind it, a rosbridge ``subscribe`` of ``topic``."""
    upgrade = (
        f"GET /rosbridge HTTP/1.1\r\nHost: {authority}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    subscribe = json.dumps({"op": "subscribe", "id": "stalled", "topic": topic})
    return upgrade.encode() + websocket_text_frame(subscribe)


def open_reader(kind: str, *, grpc_address: str, http_address: str, service: str, path: str) -> socket.socket:
    """One reader of ``kind`` (``stream``, ``sse``, ``grpc``, ``session`` or ``rosbridge``) that has
    asked and will read nothing."""
    address = grpc_address if kind in ("grpc", "session") else http_address
    host, port = address.rsplit(":", 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)  # before connecting: the window
    sock.connect((host, int(port)))
    if kind in ("grpc", "session"):
        sock.sendall(grpc_listen_bytes(address, service, path, session=kind == "session"))
    elif kind == "rosbridge":
        sock.sendall(rosbridge_subscribe_bytes(address, f"/{service}/{path.replace('.', '/')}"))
    elif kind == "stream":
        sock.sendall(http_get_bytes(address, f"/api/v1/services/{service}/properties/{path}/stream"))
    else:
        sock.sendall(http_get_bytes(address, f"/api/v1/events?sel={service}/{path}"))
    return sock


def open_readers(
    kind: str, count: int, *, grpc_address: str, http_address: str, service: str, path: str
) -> list[socket.socket]:
    target = {"grpc_address": grpc_address, "http_address": http_address, "service": service, "path": path}
    return [open_reader(kind, **target) for _ in range(count)]


def close_readers(readers: list[socket.socket]) -> None:
    for sock in readers:
        sock.close()
    readers.clear()


def payload(size: int, count: int) -> bytes:
    """``size`` bytes that differ from the previous count's (a changing value)."""
    return count.to_bytes(8, "big") + bytes([count % 251]) * (size - 8)


async def set_repeatedly(
    stub: pb_grpc.PropertyServiceStub, service: str, path: str, *, size: int, rate_hz: float, seconds: float
) -> int:
    """Set ``service``/``path`` to a new ``size``-byte value ``rate_hz`` times a second; how many."""
    count = 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        count += 1
        await stub.Set(pb.SetRequest(service=service, property=path, data=payload(size, count)), timeout=30)
        await asyncio.sleep(1 / rate_hz)
    return count


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for process {pid}")


async def _measure(args: argparse.Namespace) -> None:
    from support.blobs import BLOBS_CONFIG, start_blobs

    config = BLOBS_CONFIG + f"[http]\nmax_streams_per_client = {args.readers + 4}\n" + args.extra
    with tempfile.TemporaryDirectory() as tmp:
        gw = start_blobs(Path(tmp), config, "--http", "127.0.0.1:0")
        try:
            async with grpc.aio.insecure_channel(gw.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                await set_repeatedly(stub, "blobs", "picture", size=args.size, rate_hz=args.rate, seconds=2)
                before = _rss_mb(gw.proc.pid)
                print(f"{args.kind}: RSS before {before:.0f} MB", flush=True)
                target = {"grpc_address": gw.address, "http_address": gw.http_address}
                readers = open_readers(args.kind, args.readers, **target, service="blobs", path="picture")
                await set_repeatedly(
                    stub, "blobs", "picture", size=args.size, rate_hz=args.rate, seconds=args.seconds
                )
                stalled = _rss_mb(gw.proc.pid)
                print(f"{args.kind}: RSS with {args.readers} stalled readers {stalled:.0f} MB", flush=True)
                close_readers(readers)
                await set_repeatedly(
                    stub, "blobs", "picture", size=args.size, rate_hz=args.rate, seconds=args.after
                )
                after = _rss_mb(gw.proc.pid)
                print(f"{args.kind}: RSS {args.after:g} s after they closed {after:.0f} MB", flush=True)
        finally:
            gw.stop()
            if args.log:
                print(gw.output)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--kind", choices=KINDS, default="stream")
    parser.add_argument("--readers", type=int, default=60)
    parser.add_argument("--size", type=int, default=3_900_000)
    parser.add_argument("--rate", type=float, default=2.0, help="Sets a second")
    parser.add_argument("--seconds", type=float, default=10.0, help="Setting while the readers stall")
    parser.add_argument("--after", type=float, default=10.0, help="Setting after the readers closed")
    parser.add_argument("--extra", default="", help="more config text (TOML)")
    parser.add_argument("--log", action="store_true", help="print the gateway's output at the end")
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    asyncio.run(_measure(parser.parse_args()))


if __name__ == "__main__":
    main()
