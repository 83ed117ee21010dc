"""A client's listens share one Session stream (the SDK's default), against a real gateway process.

The gateway's own metrics say how they travel: ``psgateway_open_streams`` counts Session calls
(``session``), the Listens inside them (``session_listen``) and Listen calls (``listen``).
"""

from __future__ import annotations

import asyncio
import subprocess
import urllib.request
from collections.abc import AsyncIterator

import aiohttp
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support.gateway_process import GatewayProcess, StartGateway
from support.ports import free_port
from support.psctl import PSCTL
from support.waiting import WAIT, eventually

from clients.aio import AsyncClient, Event, Mark
from clients.errors import Unavailable
from clients.sync import Client

#: Two simulated robots; a robot's ``speed`` starts at 0.5 and its ``max_speed`` at 1 (a Set of the
#: value a property has already makes no event).
ROBOTS = """
    [[services]]
    name = "scout1"
    type = "sim-robot"

    [[services]]
    name = "scout2"
    type = "sim-robot"
"""

KINDS = ("listen", "session", "session_listen")


def _open_streams(exposition: str) -> dict[str, float]:
    found = dict.fromkeys(KINDS, 0.0)
    for family in text_string_to_metric_families(exposition):
        for sample in family.samples:
            if sample.name == "psgateway_open_streams" and sample.labels["kind"] in found:
                found[sample.labels["kind"]] = sample.value
    return found


async def open_streams(gw: GatewayProcess) -> dict[str, float]:
    """The gateway's open Listen calls, Session calls and Listens inside Sessions, by kind."""
    async with aiohttp.ClientSession() as http, http.get(f"{gw.http_url}metrics") as response:
        assert response.status == 200
        return _open_streams(await response.text())


def open_streams_now(gw: GatewayProcess) -> dict[str, float]:
    """:func:`open_streams`, for a test that blocks."""
    with urllib.request.urlopen(f"{gw.http_url}metrics", timeout=WAIT) as response:
        return _open_streams(response.read().decode())


async def next_event(events: AsyncIterator[Event | Mark]) -> Event:
    item = await asyncio.wait_for(anext(events), WAIT)
    assert isinstance(item, Event), item
    return item


def counts(listen: float, session: float, session_listen: float) -> dict[str, float]:
    return {"listen": listen, "session": session, "session_listen": session_listen}


async def test_listens_share_one_session_each_gets_its_own_events_and_one_ends_alone(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process(ROBOTS)
    async with AsyncClient(gw.address, timeout=WAIT) as client:
        speed1 = client.listen("scout1", "speed")
        speed2 = client.listen("scout2", "speed")
        max1 = client.listen("scout1", "max_speed")
        firsts = [await next_event(events) for events in (speed1, speed2, max1)]
        assert [(e.service, e.property) for e in firsts] == [
            ("scout1", "speed"),
            ("scout2", "speed"),
            ("scout1", "max_speed"),
        ]
        await eventually(lambda: open_streams(gw), lambda found: found == counts(0, 1, 3))

        await client.set("scout1", "speed", 0.25)
        await client.set("scout2", "speed", 0.375)
        one, two = await next_event(speed1), await next_event(speed2)
        assert (one.service, one.property, float(one.value)) == ("scout1", "speed", 0.25)
        assert (two.service, two.property, float(two.value)) == ("scout2", "speed", 0.375)
        assert one.sequence == two.sequence == 2  # each Listen numbers its own events

        await speed1.aclose()  # sends a Cancel for that Listen only
        await eventually(lambda: open_streams(gw), lambda found: found == counts(0, 1, 2))
        await client.set("scout2", "speed", 0.75)
        await client.set("scout1", "max_speed", 1.5)
        assert float((await next_event(speed2)).value) == 0.75
        assert float((await next_event(max1)).value) == 1.5
        await speed2.aclose()
        await max1.aclose()
    await eventually(lambda: open_streams(gw), lambda found: found == counts(0, 0, 0))


async def test_separate_listens_keep_a_listen_stream_each(gateway_process: StartGateway) -> None:
    gw = gateway_process(ROBOTS)
    async with AsyncClient(gw.address, timeout=WAIT, separate_listens=True) as client:
        speed1 = client.listen("scout1", "speed")
        speed2 = client.listen("scout2", "speed")
        await next_event(speed1)
        await next_event(speed2)
        await eventually(lambda: open_streams(gw), lambda found: found == counts(2, 0, 0))
        await client.set("scout2", "speed", 0.25)
        assert float((await next_event(speed2)).value) == 0.25
        await speed1.aclose()
        await eventually(lambda: open_streams(gw), lambda found: found == counts(1, 0, 0))
        await speed2.aclose()


def test_the_blocking_client_shares_one_session_too(gateway_process: StartGateway) -> None:
    gw = gateway_process(ROBOTS)
    with Client(gw.address, timeout=WAIT) as client:
        speed1 = client.listen("scout1", "speed")
        speed2 = client.listen("scout2", "speed")
        try:
            assert next(speed1).service == "scout1"
            assert next(speed2).service == "scout2"
            assert open_streams_now(gw) == counts(0, 1, 2)
            speed1.close()
            client.set("scout2", "speed", 0.25)
            event = next(speed2)
            assert (event.service, float(event.value)) == ("scout2", 0.25)
        finally:
            speed1.close()
            speed2.close()


def test_a_dropped_session_raises_unavailable_or_resumes_on_a_new_one(gateway_process: StartGateway) -> None:
    address = f"127.0.0.1:{free_port()}"
    first = gateway_process(ROBOTS, extra_args=["--listen", address])
    with Client(address, timeout=WAIT) as client:
        plain = client.listen("scout1", "speed")
        resumed = client.listen("scout2", "speed", resume=True)
        try:
            assert not next(plain).gap
            assert not next(resumed).gap
            first.stop()
            # The Session both shared ended: the plain listen says why, the resumed one waits.
            with pytest.raises(Unavailable, match="gateway shutting down"):
                next(plain)
            second = gateway_process(ROBOTS, extra_args=["--listen", address])
            after = next(resumed)
            assert (after.service, after.gap, after.sequence) == ("scout2", True, 1)
            assert open_streams_now(second) == counts(0, 1, 1)
        finally:
            plain.close()
            resumed.close()


@pytest.mark.parametrize(
    ("extra", "expected"),
    [((), counts(0, 1, 1)), (("--separate-stream",), counts(1, 0, 0))],
    ids=["inside-a-session", "separate-stream"],
)
def test_psctl_listens_inside_a_session_unless_told_otherwise(
    gateway_process: StartGateway, extra: tuple[str, ...], expected: dict[str, float]
) -> None:
    gw = gateway_process(ROBOTS)
    listen = subprocess.Popen(
        [*PSCTL, "-t", gw.address, "listen", "scout1", "speed", "--marks", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert listen.stdout is not None
        while "-- sync" not in listen.stdout.readline():
            assert listen.poll() is None, listen.stderr.read() if listen.stderr else ""
        assert open_streams_now(gw) == expected
    finally:
        listen.terminate()
        listen.wait(timeout=WAIT)
