"""Prometheus metrics of a real gateway process: scrape, call as a user would, scrape again.

Each test reads ``/metrics`` with prometheus_client's own parser (so the exposition
parses), does calls over gRPC and HTTP against a line-protocol device played on a
real TCP socket, and checks that the counters moved by exactly what was done.
"""

from __future__ import annotations

import asyncio
import re

import aiohttp
import grpc
from prometheus_client.parser import text_string_to_metric_families
from scripted_device import ScriptedDevice, tcp_scripted
from support.gateway_process import GatewayProcess, StartGateway
from support.waiting import wait_until

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 10.0
THERM = "HELLO 1 name=therm type=sensor push=1 maxline=256"
#: Quick reconnects and keep-alives, so that a drop shows within a test's patience.
OPTIONS = "{ timeout = 5.0, backoff_initial = 0.05, backoff_max = 0.2 }"

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


async def scrape(url: str) -> Samples:
    """Every sample of ``url`` (a /metrics endpoint), parsed by prometheus_client's parser."""
    async with aiohttp.ClientSession() as session, session.get(url) as response:
        assert response.status == 200, await response.text()
        assert response.headers["Content-Type"].startswith("text/plain; version=")
        text = await response.text()
    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def value(samples: Samples, name: str, **labels: str) -> float:
    """A sample's value; 0 when the series does not exist (yet)."""
    return samples.get((name, frozenset(labels.items())), 0.0)


async def start(
    gateway_process: StartGateway, url: str, extra: str = "", options: str = OPTIONS
) -> GatewayProcess:
    config = f'[[services]]\nname = "therm"\nurl = "{url}"\noptions = {options}\n{extra}'
    # Started from a thread: the device lives on this event loop and must answer while it starts.
    return await asyncio.to_thread(gateway_process, config)


async def connected(stub: pb_grpc.PropertyServiceStub) -> None:
    async def answers() -> None:
        while True:
            try:
                await stub.Get(pb.GetRequest(service="therm", property="a"), timeout=WAIT)
                return
            except grpc.aio.AioRpcError:
                await asyncio.sleep(0.05)

    await asyncio.wait_for(answers(), WAIT)


async def test_calls_streams_and_events_move_the_counters_by_what_was_done(
    gateway_process: StartGateway,
) -> None:
    device = ScriptedDevice(THERM, {"a": "1", "b": "2"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        metrics = f"{gw.http_url}metrics"
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await connected(stub)
            before = await scrape(metrics)

            for _ in range(3):
                await stub.Get(pb.GetRequest(service="therm", property="a"), timeout=WAIT)
            for _ in range(2):
                try:
                    await stub.Get(pb.GetRequest(service="nowhere", property="a"), timeout=WAIT)
                except grpc.aio.AioRpcError as exc:
                    assert exc.code() == grpc.StatusCode.NOT_FOUND
            await stub.Set(pb.SetRequest(service="therm", property="b", value="7"), timeout=WAIT)

            # A Listen: the current value, then three changes, each read before the next is made.
            listen = stub.Listen(pb.ListenRequest(service="therm", property="a"), timeout=30)
            received = 0

            async def read_events(count: int) -> None:
                nonlocal received
                while received < count:
                    message = await listen.read()
                    assert message is not grpc.aio.EOF
                    received += len(message.events)

            await asyncio.wait_for(read_events(1), WAIT)
            during = await scrape(metrics)
            for n in range(3):
                device.change("a", str(10 + n))
                await asyncio.wait_for(read_events(2 + n), WAIT)
            listening = await scrape(metrics)
            listen.cancel()

            # A Session: two Gets and a Set.
            async def requests() -> object:
                yield pb.SessionRequest(
                    requests=[
                        pb.Request(id=1, get=pb.GetRequest(service="therm", property="a")),
                        pb.Request(id=2, get=pb.GetRequest(service="therm", property="b")),
                        pb.Request(id=3, set=pb.SetRequest(service="therm", property="b", value="8")),
                    ]
                )

            session = stub.Session(requests(), timeout=WAIT)
            replies = [reply async for response in session for reply in response.replies]
            assert sorted(r.id for r in replies) == [1, 2, 3]

        async with aiohttp.ClientSession(base_url=gw.http_url) as http:
            async with http.get("/api/v1/services/therm/properties/a") as response:
                assert response.status == 200
            async with http.get("/api/v1/services/nowhere/properties/a") as response:
                assert response.status == 404

        after = await _settled(metrics)

    def moved(name: str, **labels: str) -> float:
        return value(after, name, **labels) - value(before, name, **labels)

    calls = "psgateway_grpc_calls_total"
    assert moved(calls, method="Get", code="OK") == 3
    assert moved(calls, method="Get", code="NOT_FOUND") == 2
    assert moved(calls, method="Set", code="OK") == 1
    assert moved(calls, method="Listen", code="CANCELLED") == 1
    assert moved(calls, method="Session", code="OK") == 1
    assert moved("psgateway_grpc_call_duration_seconds_count", method="Get") == 5
    assert moved("psgateway_grpc_call_duration_seconds_count", method="Set") == 1
    for call, count in (("get", 2), ("set", 1), ("listen", 0)):
        assert moved("psgateway_session_requests_total", call=call) == count
    assert value(during, "psgateway_open_streams", kind="listen") == 1
    assert value(after, "psgateway_open_streams", kind="listen") == 0
    assert value(after, "psgateway_open_streams", kind="session") == 0
    assert moved("psgateway_listen_events_sent_total") == received == 4
    assert (
        value(listening, "psgateway_listen_events_sent_total")
        - value(before, "psgateway_listen_events_sent_total")
        == 4
    )
    property_route = "GET /api/v1/services/{service}/properties/{path}"
    assert moved("psgateway_http_requests_total", route=property_route, status="200") == 1
    assert moved("psgateway_http_requests_total", route=property_route, status="404") == 1
    assert moved("psgateway_http_request_duration_seconds_count", route=property_route) == 2
    assert value(after, "psgateway_devices_connected", transport="tcp") == 1
    assert value(after, "psgateway_registry_entries", state="up", availability="ready") >= 2
    # No label carries a service or property name.
    assert not any("therm" in v or "nowhere" in v for _, labels in after for _, v in labels)


async def _settled(url: str) -> Samples:
    """A scrape once no stream is open any more (a cancelled call ends on the server a moment later)."""
    for _ in range(100):
        samples = await scrape(url)
        if not any(value(samples, "psgateway_open_streams", kind=k) for k in ("listen", "session")):
            return samples
        await asyncio.sleep(0.05)
    raise AssertionError("streams still open on the gateway")


async def test_a_device_that_drops_its_connection_shows_as_a_reconnect(gateway_process: StartGateway) -> None:
    device = ScriptedDevice(THERM, {"a": "1"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        metrics = f"{gw.http_url}metrics"
        async with grpc.aio.insecure_channel(gw.address) as channel:
            await connected(pb_grpc.PropertyServiceStub(channel))
        before = await scrape(metrics)
        assert value(before, "psgateway_device_connects_total", transport="tcp") == 1
        assert value(before, "psgateway_device_reconnects_total", transport="tcp") == 0

        assert device._writer is not None
        device._writer.close()  # the device drops the line; the gateway dials again
        await wait_until(lambda: device.connections >= 2, within=WAIT, what="dialled again")
        for _ in range(100):
            after = await scrape(metrics)
            if value(after, "psgateway_devices_connected", transport="tcp") == 1 and value(
                after, "psgateway_device_reconnects_total", transport="tcp"
            ):
                break
            await asyncio.sleep(0.05)
        assert value(after, "psgateway_device_disconnects_total", transport="tcp") == 1
        assert value(after, "psgateway_device_reconnects_total", transport="tcp") == 1
        assert value(after, "psgateway_device_connects_total", transport="tcp") == 2
        assert value(after, "psgateway_device_keepalive_failures_total", transport="tcp") == 0


async def test_a_device_that_misses_keepalives_is_counted(gateway_process: StartGateway) -> None:
    device = ScriptedDevice(THERM, {"a": "1"}, answer_pings=False)
    options = "{ timeout = 5.0, backoff_initial = 0.05, keepalive = 0.5, keepalive_timeout = 0.5 }"
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url, options=options)
        await wait_until(lambda: device.connections >= 2, within=WAIT, what="dropped and dialled again")
        for _ in range(100):
            samples = await scrape(f"{gw.http_url}metrics")
            if value(samples, "psgateway_device_keepalive_failures_total", transport="tcp") >= 1:
                break
            await asyncio.sleep(0.05)
        assert value(samples, "psgateway_device_keepalive_failures_total", transport="tcp") >= 1
        assert value(samples, "psgateway_device_disconnects_total", transport="tcp") >= 1


async def test_metrics_on_a_port_of_their_own_and_off(gateway_process: StartGateway) -> None:
    device = ScriptedDevice(THERM, {"a": "1"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url, '[metrics]\nlisten = "127.0.0.1:0"\n')
        found = re.search(r"^metrics on (http://\S+/metrics)$", gw.output, re.MULTILINE)
        assert found, gw.output
        own = await scrape(found.group(1))
        assert value(own, "psgateway_devices", transport="tcp") == 1

        off = await start(gateway_process, url, "[metrics]\nenabled = false\n")
        async with aiohttp.ClientSession() as session, session.get(f"{off.http_url}metrics") as response:
            assert response.status == 404


async def test_with_rules_only_who_may_read_the_registry_list_scrapes(gateway_process: StartGateway) -> None:
    rules = '[[rules]]\nsubject = "*"\nservice = "therm"\noperations = ["read"]\neffect = "permit"\n'
    device = ScriptedDevice(THERM, {"a": "1"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url, rules)
        async with aiohttp.ClientSession() as session, session.get(f"{gw.http_url}metrics") as response:
            assert response.status in (401, 403), await response.text()
            assert "registry" in await response.text()


async def test_values_a_throttled_listen_never_saw_are_counted_as_conflated(
    gateway_process: StartGateway,
) -> None:
    device = ScriptedDevice(THERM, {"a": "0"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        metrics = f"{gw.http_url}metrics"
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await connected(stub)
            before = await scrape(metrics)
            options = pb.ListenOptions()
            options.min_interval.FromMilliseconds(1500)
            listen = stub.Listen(pb.ListenRequest(service="therm", property="a", options=options), timeout=30)
            events: list[pb.Event] = []

            async def read_until(value_: str) -> None:
                while not events or events[-1].value != value_:
                    message = await listen.read()
                    assert message is not grpc.aio.EOF
                    events.extend(message.events)

            await asyncio.wait_for(read_until("0"), WAIT)
            for n in range(1, 7):  # one goes at once, the rest wait out the interval: only the last is sent
                device.change("a", str(n))
            await asyncio.wait_for(read_until("6"), WAIT)
            after = await scrape(metrics)
            listen.cancel()

    conflated = sum(event.conflated for event in events)
    assert conflated > 0, events
    moved = value(after, "psgateway_listen_events_conflated_total") - value(
        before, "psgateway_listen_events_conflated_total"
    )
    assert moved == conflated
    sent = value(after, "psgateway_listen_events_sent_total") - value(
        before, "psgateway_listen_events_sent_total"
    )
    assert sent == len(events)
