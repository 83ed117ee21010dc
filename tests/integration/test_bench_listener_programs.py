"""Part (t)'s listener programs against real gateway processes: the Go one counts as the Python one does.

``bench/go_listeners`` (built offline from Debian's Go sources by the code the
benchmark uses, into build/go-listeners) and ``python -m bench.fanout_listeners``
run the same scenario, driven by the benchmark's own :class:`bench.cluster.ListenerProcess`:
streams spread over two gateways (the second forwarding ``bench`` from the
first, as in part (t)), at most 25 a TCP connection, every Set counted on every
stream (delivered or conflated), and the streams of a gateway that goes away
counted as ended. Without Go the Go cases skip and say what is missing.
"""

from __future__ import annotations

import asyncio
import math
import subprocess
from typing import Any

import grpc
import psutil
import pytest
from support.gateway_process import StartGateway

from bench.cluster import FORWARDED_SERVICE, ORIGIN_SERVICE, ListenerProcess
from bench.cluster_listeners import (
    PYTHON_LISTENERS,
    ListenerBuildError,
    ListenerProgram,
    build_go_listeners,
    go_missing,
)
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

# A cold Go build takes about 5 s; the scenario about 10 s on a loaded machine.
pytestmark = pytest.mark.timeout(300)

STREAMS = 60  # 30 a gateway: a connection of 25 streams and one of 5 on each
SETS = 40
CALL_TIMEOUT = 10.0
#: Seconds a listener may take to read what the gateways sent before it is told ``stop``: the Go
#: listeners read every 5 ms, and a loaded machine may hold a process back for much longer.
SETTLE = 1.5
#: The time limit of a listener that is never told anything.
LIMIT = 5.0


@pytest.fixture(scope="module")
def go_program() -> ListenerProgram:
    """The Go listeners, built as the benchmark builds them; the test skips, saying why, without Go."""
    try:
        return asyncio.run(build_go_listeners())
    except ListenerBuildError as error:
        if go_missing():  # the error names what is missing and how tests/run.sh installs it
            print(error)
            pytest.skip(str(error))
        pytest.fail(str(error), pytrace=False)


@pytest.fixture(params=["go", "python"])
def program(request: pytest.FixtureRequest) -> ListenerProgram:
    if request.param == "python":
        return PYTHON_LISTENERS
    go: ListenerProgram = request.getfixturevalue("go_program")
    return go


def _tcp_connections_to(pid: int, address: str) -> int:
    """The process's TCP connections to ``address`` (grpc's C core dials 127.0.0.1 as ::ffff:127.0.0.1)."""
    host, port = address.rsplit(":", 1)
    return sum(
        1
        for c in psutil.Process(pid).net_connections(kind="tcp")
        if c.raddr and c.raddr.ip.removeprefix("::ffff:") == host and c.raddr.port == int(port)
    )


async def _set_and_see(address: str, other: str, count: int) -> None:
    """``count`` Sets of bench/value on ``address``; back once a Listen on ``other`` saw the last."""
    last = f"v{count}"
    async with grpc.aio.insecure_channel(address) as channel, grpc.aio.insecure_channel(other) as seen:
        stub = pb_grpc.PropertyServiceStub(channel)
        watch = pb_grpc.PropertyServiceStub(seen).Listen(
            pb.ListenRequest(service=SERVICE, property=VALUE_PROPERTY)
        )
        try:
            for n in range(1, count + 1):
                await stub.Set(
                    pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value=f"v{n}"),
                    timeout=CALL_TIMEOUT,
                )
            async with asyncio.timeout(CALL_TIMEOUT):
                async for response in watch:
                    if any(event.value == last for event in response.events):
                        break
        finally:
            watch.cancel()


async def test_counts_every_set_on_every_stream_and_the_streams_that_end(
    program: ListenerProgram, gateway_process: StartGateway
) -> None:
    origin = gateway_process(ORIGIN_SERVICE)
    forwarding = gateway_process(FORWARDED_SERVICE.format(service=SERVICE, origin=origin.address))
    spread = [origin.address, forwarding.address]
    listener = await ListenerProcess.start(program, spread, STREAMS, 1, 120.0)
    try:
        await listener.ready()
        # Stream k goes to spread[(1 + k) % 2]: 30 streams each, on ceil(30 / 25) = 2 connections each.
        for address in spread:
            assert _tcp_connections_to(listener.process.pid, address) == math.ceil(STREAMS / 2 / 25)
        listener.tell("start")
        await _set_and_see(origin.address, forwarding.address, SETS)
        await asyncio.sleep(SETTLE)
        # The forwarding gateway goes away: its 30 streams end, the origin's go on.
        forwarding.stop()
        await asyncio.sleep(SETTLE)
        listener.tell("stop")
        figures: dict[str, Any] = await listener.figures()
    finally:
        await listener.stop()
    assert set(figures) == {"events", "conflated", "ended"}, figures
    # Every Set reached every stream: delivered, or conflated by a gateway into a later value.
    assert figures["events"] + figures["conflated"] == STREAMS * SETS, figures
    assert figures["events"] > 0 and figures["ended"] == STREAMS // 2, figures


async def test_a_stream_refused_before_its_sync_marker_fails_the_process(
    program: ListenerProgram, gateway_process: StartGateway
) -> None:
    without_bench = gateway_process(
        '[[services]]\nname = "other"\ntype = "bench.gateway_server:BenchTarget"\n'
    )
    listener = await ListenerProcess.start(program, [without_bench.address], 3, 0, 60.0)
    try:
        async with asyncio.timeout(CALL_TIMEOUT * 3):
            code = await listener.process.wait()
        assert listener.process.stderr is not None
        said = (await listener.process.stderr.read()).decode(errors="replace")
    finally:
        await listener.stop()
    assert code == 1, said
    assert "sync marker" in said and ("NOT_FOUND" in said or "grpc-status 5" in said), said


async def test_end_of_commands_or_the_time_limit_ends_the_process(
    program: ListenerProgram, gateway_process: StartGateway
) -> None:
    origin = gateway_process(ORIGIN_SERVICE)
    quits = await ListenerProcess.start(program, [origin.address], 2, 0, 60.0)
    waits = await ListenerProcess.start(program, [origin.address], 2, 0, LIMIT)
    try:
        await quits.ready()
        assert quits.process.stdin is not None
        quits.process.stdin.close()  # end of file before ``stop``: the benchmark went away
        async with asyncio.timeout(CALL_TIMEOUT):
            assert await quits.process.wait() == 1
        async with asyncio.timeout(LIMIT + CALL_TIMEOUT):  # no command at all: the limit ends it
            assert await waits.process.wait() == 1
        assert waits.process.stderr is not None
        assert f"gave up after {LIMIT:g} s" in (await waits.process.stderr.read()).decode()
    finally:
        await quits.stop()
        await waits.stop()


def test_bad_options_exit_2_and_say_what_is_wrong(go_program: ListenerProgram) -> None:
    for options in (["--streams", "3"], ["--spread", "127.0.0.1:1", "--streams", "0"]):
        done = subprocess.run(
            [*go_program.command, *options], capture_output=True, text=True, timeout=30, check=False
        )
        assert done.returncode == 2, done
        assert "--spread needs an address" in done.stderr, done.stderr
