"""A wildcard Listen on a registry of 300 services: a real gateway process, every front end.

300 simulated sensors from the config make the registry's ``properties`` list about 110,000
characters, past the 64 KiB a value may hold (it used to be what a ``services.*.state``
Listen was expanded from, and it matched nothing). The Listen matches every service through
the SDK (a Session), a gRPC Listen stream, the HTTP event stream and ``psctl listen``, and
follows a device registered after it opened. A Get of ``properties`` answers the whole list;
the SDK's list parser refuses it, naming the limit.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import aiohttp
import grpc
import pytest
from line_device_support import tcp_device
from support.gateway_process import GatewayProcess, start_gateway
from support.psctl import psctl
from support.sse import SseReader

from clients import SYNC, AsyncClient, Event, ValueFormatError
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.values import MAX_VALUE_LENGTH

SENSORS = 300
#: Every sensor's entry and the registry's own.
ENTRIES = SENSORS + 1
WAIT = 60.0
PATTERN = "services.*.state"


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    """One gateway serving ``SENSORS`` simulated sensors (sampling once every 10 s: quiet)."""
    entries = "".join(
        f'[[services]]\nname = "sensor{i:03d}"\ntype = "sim-sensor"\noptions = {{ rate_hz = 0.1 }}\n'
        for i in range(SENSORS)
    )
    gw = start_gateway(tmp_path_factory.mktemp("big-registry"), entries)
    yield gw
    gw.stop()


def expected_paths() -> set[str]:
    return {f"services.sensor{i:03d}.state" for i in range(SENSORS)} | {"services.registry.state"}


async def test_the_sdk_matches_every_service_and_one_registered_later(gateway: GatewayProcess) -> None:
    async with AsyncClient(gateway.address, timeout=WAIT) as client:
        listing = await client.get("registry", "properties")
        assert isinstance(listing, str) and len(listing) > MAX_VALUE_LENGTH
        stream = client.listen("registry", PATTERN, marks=True)
        snapshot: dict[str, str] = {}
        async for item in stream:
            if item is SYNC:
                break
            assert isinstance(item, Event)
            snapshot[item.property] = item.value
        assert set(snapshot) == expected_paths() and set(snapshot.values()) == {"up"}
        with tcp_device("--service", "sim-robot", "--name", "late") as (host, port):
            await client.set("registry", "services.late", f"tcp://{host}:{port}")
            async for item in stream:
                assert isinstance(item, Event)
                if item.property == "services.late.state" and item.value == "up":
                    break
            await client.set("registry", "services.late", "")
        await stream.aclose()


async def test_a_grpc_listen_stream_matches_every_service(gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        call = stub.Listen(pb.ListenRequest(service="registry", property=PATTERN), timeout=WAIT)
        seen: set[str] = set()
        async for response in call:
            seen.update(e.property for e in response.events)
            if response.sync:
                break
        call.cancel()
    assert seen == expected_paths()


async def test_the_http_event_stream_matches_every_service(gateway: GatewayProcess) -> None:
    async with (
        aiohttp.ClientSession(base_url=gateway.http_url) as http,
        http.get("/api/v1/events", params=[("sel", f"registry/{PATTERN}")]) as response,
    ):
        assert response.status == 200
        snapshot = await SseReader(response).values_until_sync(within=WAIT)
    assert {m.data["path"] for m in snapshot} == expected_paths()


def test_psctl_listen_prints_every_service(gateway: GatewayProcess) -> None:
    done = psctl(
        gateway.address, "--json", "listen", "registry", PATTERN, "--count", str(ENTRIES), timeout=WAIT
    )
    assert done.returncode == 0, done.stderr
    assert {json.loads(line)["property"] for line in done.stdout.splitlines()} == expected_paths()


async def test_a_get_of_properties_answers_the_whole_list_which_the_sdk_parser_refuses(
    gateway: GatewayProcess,
) -> None:
    async with AsyncClient(gateway.address, timeout=WAIT) as client:
        listing = await client.get("registry", "properties")
        assert isinstance(listing, str)
        assert all(f"services.sensor{i:03d}.state" in listing for i in range(SENSORS))  # nothing cut off
        with pytest.raises(ValueFormatError) as err:
            await client.properties("registry")
    assert f"the limit is {MAX_VALUE_LENGTH} characters" in str(err.value)
