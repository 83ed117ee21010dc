"""The benchmark's peers: servers and clients stay on loopback, and a peer without its client is skipped.

The OPC UA and Zenoh peers of ``python -m bench`` (part (s)) are real
servers in processes of their own. Zenoh scouts for peers by UDP multicast
unless told not to; these tests look at the sockets the peers' processes and
their clients hold while they answer, and find every one on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import psutil
import pytest
from support.waiting import eventually

from bench.peers import BY_NAME, missing
from bench.servers import ServerProcess

ROOT = Path(__file__).resolve().parents[2]
LOOPBACK = "127.0.0.1"


def _skip_without(peer: str) -> None:
    reason = missing(BY_NAME[peer])
    if reason is not None:
        pytest.skip(reason)


def _inet(process: psutil.Process) -> list[Any]:
    return list(process.net_connections(kind="inet"))


def _off_loopback(connections: list[Any]) -> list[str]:
    """Every socket that is UDP, or whose local or remote address is not 127.0.0.1, described."""
    wrong = []
    for conn in connections:
        addresses = [conn.laddr.ip] + ([conn.raddr.ip] if conn.raddr else [])
        if conn.type == socket.SOCK_DGRAM or any(ip != LOOPBACK for ip in addresses):
            wrong.append(f"{conn.type.name} {conn.laddr} -> {conn.raddr or '-'} ({conn.status})")
    return wrong


async def test_the_zenoh_peer_and_its_clients_hold_only_loopback_tcp_sockets() -> None:
    _skip_without("zenoh")
    import zenoh

    from bench.peer_zenoh_server import KEY, loopback_config

    me = psutil.Process()
    before = {conn.fd for conn in _inet(me)}
    server = await ServerProcess.start("zenoh", ["bench.peer_zenoh_server", "--listen", "127.0.0.1:0"])
    try:
        session = zenoh.open(loopback_config("client", connect=[f"tcp/{server.address}"]))
        try:
            publisher = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)

            async def put_and_get() -> list[str]:
                publisher.put("42")
                replies = await asyncio.to_thread(lambda: list(session.get(KEY, timeout=5.0)))
                return [reply.ok.payload.to_string() for reply in replies if reply.ok is not None]

            # The peer learns of the client's declarations on its own time; then it answers what was put:
            # the sockets are in use, not only open.
            await eventually(put_and_get, lambda values: values == ["42"], what="the peer answers the put")
            mine = [conn for conn in _inet(me) if conn.fd not in before]
            theirs = _inet(psutil.Process(server.pid))
            assert mine and theirs, (mine, theirs)
            assert _off_loopback(mine) == []
            assert _off_loopback(theirs) == []
            publisher.undeclare()
        finally:
            session.close()
    finally:
        await server.stop()


async def test_the_opcua_server_holds_only_loopback_sockets_while_it_answers() -> None:
    _skip_without("opcua")
    from asyncua import Client, ua

    from bench.peer_opcua_server import ENDPOINT_PATH, NAMESPACE, VALUE_NODE

    server = await ServerProcess.start("opcua", ["bench.peer_opcua_server", "--listen", "127.0.0.1:0"])
    try:
        async with Client(f"opc.tcp://{server.address}{ENDPOINT_PATH}", timeout=10) as client:
            node = client.get_node(ua.NodeId(VALUE_NODE, await client.get_namespace_index(NAMESPACE)))
            await node.write_value(ua.Variant("42", ua.VariantType.String))
            assert await node.read_value() == "42"
            theirs = _inet(psutil.Process(server.pid))
            assert any(conn.status == psutil.CONN_ESTABLISHED for conn in theirs), theirs
            assert _off_loopback(theirs) == []
    finally:
        await server.stop()


def test_a_peer_whose_client_cannot_be_imported_is_skipped_with_the_reason(tmp_path: Path) -> None:
    # A module named zenoh that refuses to import stands first on the path: as if the wheel were absent.
    (tmp_path / "zenoh.py").write_text('raise ImportError("no wheel for this machine")\n')
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--quick", "--strict", "--parts", "zenoh"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"},
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "zenoh  skipped: eclipse-zenoh cannot be imported (no wheel for this machine)" in done.stdout, (
        done.stdout
    )
