"""Bounded connections on every port, against a real gateway process: a flood of idle connections
from one address leaves a bystander's gRPC Get, HTTP Get and a dialling-in device working; the
metrics port checks Host; a burst of calls meets a named limit, never a bare CANCELLED; an
accept that finds no descriptor pauses and says so once.

The caps are lowered through the config so that a few hundred connections prove what the
defaults do for thousands (docs/security.md, "Bounded connections"). The flood comes from
127.0.0.2 (every 127/8 address is loopback on Linux), the bystander from 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import resource
import socket

import aiohttp
import grpc
import pytest
from line_device_support import device_process
from scripted_device import ScriptedDevice, tcp_scripted
from support.bystander import get_p99, registry_state, rss_mb
from support.gateway_process import GatewayProcess, StartGateway
from support.ports import free_port
from support.waiting import eventually, wait_until

from gateway.connections import BoundedListener, ConnectionCaps
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 20.0
FLOOD = 300
PER_ADDRESS = 20
ATTACKER = "127.0.0.2"

Streams = tuple[asyncio.StreamReader, asyncio.StreamWriter]


async def flood(port: int, count: int = FLOOD) -> list[Streams]:
    """``count`` connections to ``port`` from the attacker's address that send nothing."""
    return [await asyncio.open_connection("127.0.0.1", port, local_addr=(ATTACKER, 0)) for _ in range(count)]


async def first_bytes(streams: list[Streams], within: float = 1.0) -> list[bytes | None]:
    """What each connection reads within ``within`` seconds: its bytes to the end (b"" when it was
    closed without a word), or None while it is still open."""

    async def read(reader: asyncio.StreamReader) -> bytes | None:
        try:
            return await asyncio.wait_for(reader.read(), within)
        except TimeoutError:
            return None
        except ConnectionError:
            return b""

    return list(await asyncio.gather(*(read(reader) for reader, _ in streams)))


def close_all(streams: list[Streams]) -> None:
    for _, writer in streams:
        writer.close()


async def http_get(gw: GatewayProcess, path: str) -> tuple[int, str]:
    async with (
        aiohttp.ClientSession(base_url=gw.http_url) as session,
        session.get(path, timeout=aiohttp.ClientTimeout(total=WAIT)) as response,
    ):
        return response.status, await response.text()


async def test_idle_connections_from_one_address_leave_every_port_working_for_a_bystander(
    gateway_process: StartGateway,
) -> None:
    line_port = free_port()
    gw = gateway_process(f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"
        max_connections = 100
        handshake_timeout = 2.0
        [http]
        max_connections_per_address = {PER_ADDRESS}
        idle_timeout = 3.0
        [limits]
        line_max_connections_per_address = {PER_ADDRESS}
        [[services]]
        name = "bot"
        type = "sim-robot"
    """)
    http_port = int(gw.http_address.rpartition(":")[2])
    grpc_port = int(gw.address.rpartition(":")[2])
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await get_p99(stub, "bot", "location")
        rss_before, p99_before = rss_mb(gw.proc.pid), await get_p99(stub, "bot", "location")

        http_flood, line_flood, grpc_flood = (
            await flood(http_port),
            await flood(line_port),
            await flood(grpc_port),
        )
        http_read, line_read, grpc_read = await asyncio.gather(
            first_bytes(http_flood), first_bytes(line_flood), first_bytes(grpc_flood)
        )
        # Past the per-address cap, the HTTP port answers 503 naming the option and closes.
        assert http_read.count(None) == PER_ADDRESS
        refused = [answer for answer in http_read if answer is not None]
        assert all(answer.startswith(b"HTTP/1.1 503 ") for answer in refused)
        assert b"http.max_connections_per_address" in refused[0]
        # The line listener says ERR 8 (RESOURCE_EXHAUSTED) to every connection past it.
        assert line_read.count(None) == PER_ADDRESS
        refused_lines = [
            answer for answer in line_read if answer is not None and answer.startswith(b"ERR 8 ")
        ]
        assert refused_lines and b"limits.line_max_connections_per_address" in refused_lines[0]
        # grpc has no per-address cap: its share of open files (gateway.max_connections) holds.
        assert grpc_read.count(None) <= 100

        # The bystander: a gRPC Get on a connection of its own, an HTTP Get, a device dialling in.
        reply = await stub.Get(pb.GetRequest(service="bot", property="location"), timeout=WAIT)
        assert reply.value
        status, body = await http_get(gw, "/api/v1/services/bot/properties/location")
        assert status == 200, body
        with device_process(
            "--service", "sim-robot", "--name", "rover", "--connect", f"127.0.0.1:{line_port}"
        ):
            assert (
                await eventually(
                    lambda: registry_state(stub, "rover"), lambda s: s == "up", within=WAIT, what="rover"
                )
                == "up"
            )

        # What was let in is closed once it stayed silent: idle_timeout (HTTP), handshake_timeout
        # (gRPC); nothing of the flood is left open.
        http_after, grpc_after = await asyncio.gather(
            first_bytes(http_flood, WAIT), first_bytes(grpc_flood, WAIT)
        )
        assert None not in http_after
        assert None not in grpc_after
        close_all(http_flood + line_flood + grpc_flood)

        rss_after, p99_after = rss_mb(gw.proc.pid), await get_p99(stub, "bot", "location")
    figures = (rss_before, rss_after, p99_before * 1e3, p99_after * 1e3)
    print("RSS {:.1f} -> {:.1f} MB; bystander Get p99 {:.1f} -> {:.1f} ms".format(*figures))
    assert rss_after - rss_before < 30
    assert p99_after < 0.2
    # Refusals are summed up in one line per interval, never one line per connection.
    assert gw.output.count("http.listen: refused") <= 2
    assert "out of system resource" not in gw.output
    assert "Traceback" not in gw.output


async def test_a_flood_of_connections_past_the_total_cap_is_closed_at_once(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process("""
        [http]
        max_connections = 30
        max_connections_per_address = 1000
        [[services]]
        name = "bot"
        type = "sim-robot"
    """)
    http_port = int(gw.http_address.rpartition(":")[2])
    held = await flood(http_port, 60)
    answers = await first_bytes(held)
    assert answers.count(None) == 30
    assert b"http.max_connections" in next(a for a in answers if a is not None)
    close_all(held)
    # Closed connections give their places back: a bystander's Get is answered again.
    status = 0
    for _ in range(50):
        status, _ = await http_get(gw, "/api/v1/services/bot/properties/location")
        if status == 200:
            break
        await asyncio.sleep(0.1)
    assert status == 200


async def test_the_metrics_port_refuses_a_host_that_is_not_loopback(gateway_process: StartGateway) -> None:
    gw = gateway_process('[metrics]\nlisten = "127.0.0.1:0"\n')
    found = re.search(r"^metrics on http://(\S+)/metrics$", gw.output, re.MULTILINE)
    assert found is not None, gw.output
    address = found.group(1)
    url = f"http://{address}/metrics"
    async with aiohttp.ClientSession() as session:
        async with session.get(url, headers={"Host": "evil.example"}) as rebound:
            assert rebound.status == 403
            error = (await rebound.json())["error"]
            assert error["code"] == "PERMISSION_DENIED" and "loopback" in error["message"]
        async with session.get(
            url, headers={"Host": "evil.example", "Origin": "http://evil.example"}
        ) as cors:
            assert cors.status == 403
        async with session.get(url) as own:
            assert own.status == 200
            assert "psgateway_" in await own.text()


async def test_a_burst_of_gets_on_one_connection_is_answered_or_refused_by_name_never_cancelled(
    gateway_process: StartGateway,
) -> None:
    # A device that takes 20 ms a request (one at a time, as a small microcontroller does) keeps
    # far more than max_calls Gets of the burst in flight together, however fast the machine.
    device = ScriptedDevice("HELLO 1 name=bot type=sensor push=1", {"temp": "21.5"}, delay=0.02)
    async with tcp_scripted(device) as url:
        gw = gateway_process(f"""
            [limits]
            max_calls = 20
            [[services]]
            name = "bot"
            url = "{url}"
        """)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            request = pb.GetRequest(service="bot", property="temp")
            await stub.Get(request, timeout=WAIT)
            results = await asyncio.gather(
                *(stub.Get(request, timeout=60) for _ in range(2000)), return_exceptions=True
            )
    codes = [r.code() if isinstance(r, grpc.aio.AioRpcError) else grpc.StatusCode.OK for r in results]
    counted = {code.name: codes.count(code) for code in set(codes)}
    refused = [r for r in results if isinstance(r, grpc.aio.AioRpcError)]
    assert set(codes) <= {grpc.StatusCode.OK, grpc.StatusCode.RESOURCE_EXHAUSTED}, (counted, refused[:1])
    assert any("[limits] max_calls" in (r.details() or "") for r in refused), (counted, refused[:1])
    assert counted["OK"] >= 20, counted


async def test_5000_concurrent_gets_on_one_connection_all_succeed_with_the_default_limits(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process("""
        [[services]]
        name = "bot"
        type = "sim-robot"
    """)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        request = pb.GetRequest(service="bot", property="location")
        results = await asyncio.gather(
            *(stub.Get(request, timeout=120) for _ in range(5000)), return_exceptions=True
        )
    failed = [r for r in results if isinstance(r, BaseException)]
    assert failed == [], f"{len(failed)} of 5000 failed, e.g. {failed[0]!r}"


def _lowest_free_descriptor() -> int:
    probe = os.open(os.devnull, os.O_RDONLY)  # the kernel's own choice: the lowest number not open
    os.close(probe)
    return probe


async def test_an_accept_that_finds_no_descriptor_backs_off_and_is_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # In this process: the test takes the descriptors away itself, then gives them back.
    served: list[asyncio.BaseTransport] = []

    class Hello(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            served.append(transport)

    listener = BoundedListener(Hello, ConnectionCaps(100, 100, "t.max", "t.per"), "test.listen")
    host, port = await listener.start("127.0.0.1", 0)
    clients = [socket.create_connection((host, port)) for _ in range(5)]  # wait in the backlog
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    # A new descriptor takes the lowest free number, so a limit at that number leaves none to
    # accept with, whatever holes a long-lived process (a pytest worker) has among its numbers.
    lowest_free = _lowest_free_descriptor()
    try:
        with caplog.at_level(logging.WARNING, logger="gateway.connections"):
            resource.setrlimit(resource.RLIMIT_NOFILE, (lowest_free, hard))  # none left to accept with
            await asyncio.sleep(1.0)
            resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
            await wait_until(lambda: len(served) == 5, within=WAIT, what="5 connections served")
        failures = [r.getMessage() for r in caplog.records if "accept failed" in r.getMessage()]
        # One line for a second of failing accepts (asyncio's own loop wrote one an accept,
        # and retried as many times), the pause doubling from 50 ms meanwhile.
        assert len(failures) == 1, failures
        assert "Too many open files" in failures[0] and "accepting again in 0.05 s" in failures[0]
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        for client in clients:
            client.close()
        for transport in served:
            transport.close()
        await listener.aclose()


async def test_refusals_after_the_first_are_logged_when_the_interval_ends_and_at_close(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # In this process, with a short interval: one connection is the port's share, the rest are refused.
    listener = BoundedListener(
        asyncio.Protocol, ConnectionCaps(1, 1, "t.max", "t.per"), "test.listen", log_interval=1.0
    )
    host, port = await listener.start("127.0.0.1", 0)
    clients: list[socket.socket] = []

    def refusals() -> list[str]:
        return [r.getMessage() for r in caplog.records if "test.listen: refused" in r.getMessage()]

    try:
        with caplog.at_level(logging.WARNING, logger="gateway.connections"):
            clients.append(socket.create_connection((host, port)))
            await wait_until(lambda: listener.open == 1, within=WAIT, what="the one connection admitted")
            clients.append(socket.create_connection((host, port)))
            await wait_until(lambda: len(refusals()) == 1, within=WAIT, what="the first refusal's line")
            clients += [socket.create_connection((host, port)) for _ in range(2)]
            for client in clients[-2:]:
                assert await asyncio.to_thread(client.recv, 1) == b""  # closed at once: refused
            # No further refusal comes: the timer writes the two counted.
            await wait_until(lambda: len(refusals()) == 2, within=WAIT, what="the timer's line")
            clients.append(socket.create_connection((host, port)))
            assert await asyncio.to_thread(clients[-1].recv, 1) == b""  # refused and counted, not yet written
            await listener.aclose()
        first, timed, closing = refusals()
        assert first.startswith("test.listen: refused 1 connection(s)"), first
        assert timed.startswith("test.listen: refused 2 connection(s)"), timed
        assert closing.startswith("test.listen: refused 1 connection(s)"), closing
    finally:
        for client in clients:
            client.close()
        await listener.aclose()
