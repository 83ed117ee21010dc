"""A client cannot make grpc's C core write a log line per connection (docs/security.md).

Raw HTTP/2 connections each send the preface, SETTINGS and GOAWAY(ENHANCE_YOUR_CALM,
"ping_timeout"): with grpc's default verbosity each one added an INFO line
(``chttp2_transport.cc ... Got goaway [11]``) to the gateway's log.
"""

from __future__ import annotations

import socket
import struct

import pytest
from support.gateway_process import StartGateway

_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
_SETTINGS, _PING, _GOAWAY = 0x4, 0x6, 0x7
_ACK = 0x1
_ENHANCE_YOUR_CALM = 0xB
CONNECTIONS = 20


def _frame(kind: int, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload))[1:] + bytes((kind, 0)) + struct.pack(">I", 0) + payload


def _read_exactly(conn: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = conn.recv(size - len(data))
        assert chunk, "the gateway closed the connection before it answered the PING"
        data += chunk
    return data


def send_goaway(address: str) -> None:
    """One connection that says goodbye at once, then a PING: its ACK means the gateway has read
    (and handled) the GOAWAY, since HTTP/2 frames on a connection are read in order."""
    host, port = address.rsplit(":", 1)
    goaway = struct.pack(">II", 0, _ENHANCE_YOUR_CALM) + b"ping_timeout"
    with socket.create_connection((host, int(port)), timeout=10) as conn:
        conn.sendall(_PREFACE + _frame(_SETTINGS, b"") + _frame(_GOAWAY, goaway) + _frame(_PING, b"goaway!!"))
        while True:
            header = _read_exactly(conn, 9)
            length, kind, flags = int.from_bytes(header[:3]), header[3], header[4]
            body = _read_exactly(conn, length)
            if kind == _PING and flags & _ACK and body == b"goaway!!":
                return


def test_connections_that_send_goaway_do_not_each_write_a_log_line(
    gateway_process: StartGateway, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("GRPC_VERBOSITY", raising=False)  # the gateway's own default, as a user runs it
    gw = gateway_process("")
    before = len(gw.output.splitlines())
    for _ in range(CONNECTIONS):
        send_goaway(gw.address)
    gw.wait_ready()  # still serving; a health check's round trip also lets the last closes be logged
    gw.stop()
    grown = gw.output.splitlines()[before:]
    assert [line for line in grown if "goaway" in line.lower()] == []
    assert len(grown) < CONNECTIONS, grown
