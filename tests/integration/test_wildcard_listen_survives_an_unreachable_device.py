"""A wildcard Listen over a device that cannot be reached: a real gateway process, a real TCP device.

The device (a simulated robot served on the line protocol) is killed before the Listen opens.
A wildcard (`*/location`, a group's `robots.*.location`) opens anyway with the other services'
values and `sync`; when the device is started again on the same port, its location arrives
marked `gap` and is followed from then on. An exact selector on the dead device still fails
with UNAVAILABLE. Through the SDK (gRPC) and through the HTTP event stream (SSE).
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
from collections.abc import AsyncIterator, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field

import aiohttp
import pytest
from line_device_support import device_process
from support.gateway_process import GatewayProcess, StartGateway
from support.sse import SseReader
from support.waiting import eventually, wait_until

from clients import SYNC, AsyncClient, Event, Mark, Unavailable

#: Seconds any one wait may take: the gateway tries a skipped device again at most every 10 s, and
#: the device process may take seconds to start again on a loaded machine.
WAIT = 35.0
EVENTS = "/api/v1/events"
MOVETO = "<marker><location>(4 1)</location></marker>"


@dataclass
class Rig:
    """The gateway, the device's port, and the device process of the moment."""

    gateway: GatewayProcess
    port: int
    device: subprocess.Popen[str]
    #: Every device process started again; each is ended when the test ends.
    restarts: ExitStack = field(default_factory=ExitStack)

    def kill_device(self) -> None:
        """The device dies: a power cut, no goodbye."""
        os.kill(self.device.pid, signal.SIGKILL)
        self.device.wait(5)

    def restart_device(self) -> None:
        """The device comes back on the same port."""
        self.device, _ = self.restarts.enter_context(device_process(*rover_args(f"127.0.0.1:{self.port}")))


def rover_args(address: str) -> list[str]:
    return ["--service", "sim-robot", "--name", "rover", "--option", "start=[3, 0]", "--tcp", address]


@pytest.fixture
def rig(gateway_process: StartGateway) -> Iterator[Rig]:
    """A gateway with scout1 (in process), rover (a device on TCP, dead) and a group of both."""
    with device_process(*rover_args("127.0.0.1:0")) as (proc, first):
        port = int(first.rpartition(":")[2])
        gw = gateway_process(f"""
            [gateway]
            log_level = "info"
            call_timeout = 2.0

            [[services]]
            name = "scout1"
            type = "sim-robot"

            [[services]]
            name = "rover"
            url = "tcp://127.0.0.1:{port}"
            options = {{ timeout = 2.0, backoff_initial = 0.05, backoff_max = 0.3 }}

            [[services]]
            name = "swarm"
            type = "group"
            options = {{ members = ["scout1", "rover"] }}
        """)
        rig = Rig(gw, port, proc)
        rig.kill_device()
        with rig.restarts:
            yield rig


@pytest.fixture
async def client(rig: Rig) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(rig.gateway.address, timeout=5) as client:
        # The gateway has noticed: a call to the device is UNAVAILABLE now.
        await expect_unavailable(client)
        yield client


async def expect_unavailable(client: AsyncClient) -> None:
    async def probe() -> str:
        try:
            await client.get("rover", "location")
        except Unavailable as exc:
            return exc.message
        return "answered"

    await eventually(
        probe, lambda answer: answer != "answered", within=WAIT, what="the device is unreachable"
    )


async def in_log(rig: Rig, text: str) -> None:
    """Wait until the gateway's output (read by a thread of the test) shows ``text``."""
    await wait_until(lambda: text in rig.gateway.output, what=f"the log line {text!r}")


def xy(value: str) -> tuple[float, float]:
    x, y = (float(t) for t in value.strip("()").split()[:2])
    return x, y


async def test_an_exact_selector_on_the_dead_device_fails_with_unavailable(client: AsyncClient) -> None:
    with pytest.raises(Unavailable, match="rover"):
        async with asyncio.timeout(WAIT):
            async for _ in client.listen("rover", "location"):
                pass


async def test_a_wildcard_service_listen_skips_the_dead_device_and_follows_it_once_back(
    rig: Rig, client: AsyncClient
) -> None:
    items = client.listen("*", "location", marks=True)
    try:
        async with asyncio.timeout(WAIT):
            snapshot: list[Event] = []
            async for item in items:
                if item is SYNC:
                    break
                assert isinstance(item, Event)
                snapshot.append(item)
            assert {e.service for e in snapshot} == {"scout1", "swarm"}
            assert not any(e.gap for e in snapshot)
            await in_log(rig, "rover cannot be reached (UNAVAILABLE")

            rig.restart_device()
            back = await next_event(items, "rover")
            assert (back.value, back.gap) == ("(3 0 0 0 0 0)", True)

            # Followed from then on: the robot drives, its location changes event by event.
            await client.set("rover", "speed", "2")
            await client.set("rover", "behaviors.moveto", MOVETO)
            moved = await next_event(items, "rover")
            assert not moved.gap and xy(moved.value) != (3.0, 0.0)
    finally:
        await items.aclose()
    await in_log(rig, "rover answers again")


async def next_event(items: AsyncIterator[Event | Mark], service: str, path: str = "location") -> Event:
    async for item in items:
        if isinstance(item, Event) and (item.service, item.property) == (service, path):
            return item
    raise AssertionError("the stream ended")


async def test_a_device_already_followed_that_goes_away_comes_back_as_a_gap(
    rig: Rig, client: AsyncClient
) -> None:
    # As before: the proxy reconnects and marks the value after the outage as a gap; nothing in
    # between (no `removed`), and the stream stays open.
    rig.restart_device()
    items = client.listen("*", "location", marks=True)
    try:
        async with asyncio.timeout(WAIT):
            first = await next_event(items, "rover")  # in the snapshot, or once the retry reaches it
            rig.kill_device()
            await expect_unavailable(client)
            rig.restart_device()
            back = await next_event(items, "rover")
            assert (back.value, back.gap, back.removed) == (first.value, True, False)
            assert back.sequence > first.sequence
    finally:
        await items.aclose()


async def test_a_group_wildcard_listen_skips_the_dead_member_and_follows_it_once_back(
    rig: Rig, client: AsyncClient
) -> None:
    items = client.listen("swarm", "robots.*.location", marks=True)
    try:
        async with asyncio.timeout(WAIT):
            snapshot: list[Event] = []
            async for item in items:
                if item is SYNC:
                    break
                assert isinstance(item, Event)
                snapshot.append(item)
            assert [e.property for e in snapshot] == ["robots.scout1.location"]

            rig.restart_device()
            back = await next_event(items, "swarm", "robots.rover.location")
            assert (back.value, back.gap) == ("(3 0 0 0 0 0)", True)
            await client.set("rover", "speed", "2")
            await client.set("swarm", "robots.rover.behaviors.moveto", MOVETO)
            moved = await next_event(items, "swarm", "robots.rover.location")
            assert not moved.gap and xy(moved.value) != (3.0, 0.0)
    finally:
        await items.aclose()


async def test_a_group_listing_that_changes_elsewhere_while_a_member_is_away_keeps_following_it(
    rig: Rig, client: AsyncClient
) -> None:
    rig.restart_device()
    await eventually(lambda: client.get("rover", "location"), retry_on=(Unavailable,), within=WAIT)
    items = client.listen("swarm", "robots.*.location", ("swarm", "subgroups.*"), marks=True)
    try:
        async with asyncio.timeout(WAIT):
            await next_event(items, "swarm", "robots.rover.location")
            rig.kill_device()
            await expect_unavailable(client)
            # The group's property list changes elsewhere while the member is away: the wildcards
            # ask the group about that part alone, and the member's properties stay followed.
            await client.set("swarm", "subgroup", "pair", members="(scout1)")
            heard: list[Event] = []
            async for item in items:
                if isinstance(item, Event):
                    heard.append(item)
                    if item.property == "subgroups.pair":
                        break
            assert not any(e.property.startswith("robots.rover.") for e in heard)
            rig.restart_device()
            back = await next_event(items, "swarm", "robots.rover.location")
            assert (back.value, back.gap, back.removed) == ("(3 0 0 0 0 0)", True, False)
    finally:
        await items.aclose()


async def test_an_event_stream_over_http_skips_the_dead_device_and_follows_it_once_back(
    rig: Rig, client: AsyncClient
) -> None:
    params = [("sel", "*/location"), ("sel", "swarm/robots.*.location")]
    async with (
        aiohttp.ClientSession(base_url=rig.gateway.http_url) as http,
        http.get(EVENTS, params=params) as response,
    ):
        assert response.status == 200
        events = SseReader(response)
        snapshot = await events.values_until_sync(within=WAIT)
        assert sorted((m.data["service"], m.data["path"]) for m in snapshot) == [
            ("scout1", "location"),
            ("swarm", "location"),
            ("swarm", "robots.scout1.location"),
        ]

        rig.restart_device()
        wanted = {("rover", "location"), ("swarm", "robots.rover.location")}
        back = {}
        async with asyncio.timeout(WAIT):
            while not wanted <= back.keys():
                message = await events.until("value", within=WAIT)
                back.setdefault((message.data["service"], message.data["path"]), message.data)
        for key in wanted:
            assert (back[key]["value"], back[key]["gap"]) == ("(3 0 0 0 0 0)", True), key

        await client.set("rover", "speed", "2")
        await client.set("rover", "behaviors.moveto", MOVETO)
        async with asyncio.timeout(WAIT):
            while True:
                message = await events.until("value", within=WAIT)
                if message.data["service"] == "rover":
                    break
        assert not message.data["gap"] and xy(message.data["value"]) != (3.0, 0.0)


async def test_an_exact_selector_in_an_event_stream_on_the_dead_device_is_an_error_event(
    rig: Rig, client: AsyncClient
) -> None:
    async with (
        aiohttp.ClientSession(base_url=rig.gateway.http_url) as http,
        http.get(EVENTS, params=[("sel", "rover/location")]) as response,
    ):
        error = await SseReader(response).next(within=WAIT)
    assert error.event == "error" and error.data["code"] == "UNAVAILABLE"
    assert "rover" in error.data["message"]
