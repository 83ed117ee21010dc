"""The Python SDK against a real gateway process serving the demo robots and sensor."""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
from support.ports import free_port

from clients import (
    HEARTBEAT,
    SYNC,
    AsyncClient,
    Cancelled,
    Client,
    Event,
    FailedPrecondition,
    GatewayUnreachable,
    InvalidArgument,
    Marker,
    NotFound,
    PropertyServiceError,
)

MOVETO = "<marker><location>(2 1 0 0 0 0)</location></marker>"


@pytest.fixture(scope="module")
def demo_target(demo_gateway: Any) -> str:
    """Address of this module's demo gateway process (see conftest.py)."""
    return demo_gateway.address


@pytest.fixture
async def client(demo_target: str) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(demo_target, timeout=10.0) as c:
        yield c


def _xy(value: str) -> tuple[float, float]:
    x, y = (float(t) for t in value.strip("()").split()[:2])
    return x, y


async def test_directory_and_typed_helpers(client: AsyncClient) -> None:
    services = await client.services()
    assert {"scout1", "scout2", "thermo1"} <= set(services)
    props = await client.properties("scout2")
    assert "location" in props
    location = await client.get_vector("scout2", "location")
    assert isinstance(location, np.ndarray)
    assert location.shape == (6,)
    assert await client.get_number("scout2", "location.x") == location[0]
    temperature = await client.get_number("thermo1", "data")
    assert math.isfinite(temperature)
    x, y = await client.get_many([("scout2", "location.x"), ("scout2", "location.y")])
    assert (float(x), float(y)) == (location[0], location[1])


async def test_set_returns_and_stores(client: AsyncClient) -> None:
    await client.set("scout2", "speed", 0.75)
    assert await client.get_number("scout2", "speed") == 0.75
    await client.set("scout2", "actuators.led", True)
    assert await client.get("scout2", "actuators.led") == "true"


async def _drive_to(client: AsyncClient, robot: str, xy: tuple[float, float]) -> None:
    """Send ``robot`` to ``xy`` and wait until it is there."""
    async with asyncio.timeout(30):
        async for ev in client.listen(robot, "location"):
            if np.allclose(_xy(ev.value), xy):
                return
            if ev.sequence == 1:
                await client.set(robot, "behaviors.moveto", Marker.at(xy))


async def test_moveto_listen_converges_then_quiet(client: AsyncClient) -> None:
    await client.set("scout1", "speed", 5.0)
    if np.allclose((await client.get_vector("scout1", "location"))[:2], (2, 1)):
        await _drive_to(client, "scout1", (0, 0))  # left there by an earlier run against the same gateway
    stream = client.listen("scout1", "location", marks=True)
    items: list[Event] = []
    saw_sync = False
    try:
        async with asyncio.timeout(30):
            async for item in stream:
                if item is SYNC:
                    saw_sync = True
                    assert items, "the current value comes before the sync marker"
                    await client.set("scout1", "behaviors.moveto", Marker.at([2, 1, 0, 0, 0, 0]))
                    continue
                assert isinstance(item, Event)
                items.append(item)
                if saw_sync and np.allclose(_xy(item.value), (2, 1)):
                    break
        # After arriving the robot stays put: nothing more is sent.
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(0.5):
                extra = await anext(stream)
                pytest.fail(f"unexpected event after arrival: {extra}")
    finally:
        await stream.aclose()
    assert saw_sync
    assert [e.sequence for e in items] == list(range(1, len(items) + 1))
    assert all((e.service, e.property) == ("scout1", "location") for e in items)
    assert len(items) >= 3, "the robot moves in several steps"
    xs = [_xy(e.value)[0] for e in items[1:]]
    assert xs == sorted(xs), "x grows monotonically toward the target"
    assert (await client.get_vector("scout1", "location"))[:2].tolist() == pytest.approx([2, 1])


async def test_errors_have_precise_classes(client: AsyncClient) -> None:
    with pytest.raises(NotFound, match="NOT_FOUND") as unknown_service:
        await client.get("scoutX", "location")
    assert unknown_service.value.service == "scoutX"
    assert "scoutX" in str(unknown_service.value)
    with pytest.raises(NotFound):
        await client.get("scout1", "no_such_property")
    with pytest.raises(InvalidArgument, match="INVALID_ARGUMENT"):
        await client.set("scout1", "behaviors.moveto", "<marker><location>(1, 2)</location></marker>")
    with pytest.raises(InvalidArgument):
        await client.set("scout1", "speed", "fast")
    with pytest.raises(FailedPrecondition, match="FAILED_PRECONDITION"):
        await client.set("scout1", "location", "(1 2 0 0 0 0)")
    with pytest.raises(NotFound):
        async for _ in client.listen("scoutX", "location"):
            pass


async def test_listen_several_selectors_with_heartbeat(client: AsyncClient) -> None:
    stream = client.listen("scout1", "location", ("scout2", "location"), heartbeat=0.2, marks=True)
    seen: set[tuple[str, str]] = set()
    marks = []
    try:
        async with asyncio.timeout(10):
            async for item in stream:
                if isinstance(item, Event):
                    seen.add((item.service, item.property))
                else:
                    marks.append(item)
                    if item is HEARTBEAT:
                        break
    finally:
        await stream.aclose()
    assert seen == {("scout1", "location"), ("scout2", "location")}
    assert marks[0] is SYNC
    assert marks[-1] is HEARTBEAT


async def test_session_many_concurrent_calls_and_a_failure(client: AsyncClient) -> None:
    async with client.session() as s:
        results = await asyncio.gather(
            *(s.get("scout2", "location.x") for _ in range(200)),
            s.get("scout2", "no_such_property"),
            *(s.get("thermo1", "location") for _ in range(50)),
            return_exceptions=True,
        )
        failures = [r for r in results if isinstance(r, BaseException)]
        assert len(failures) == 1
        assert isinstance(failures[0], NotFound)
        assert failures[0].property == "no_such_property"
        assert len({r for r in results[:200]}) == 1
        # The session lives on after a failed request.
        await s.set("scout2", "speed", 0.5)
        assert await s.get("scout2", "speed") == "0.5"
        assert await s.get_many([("scout2", "speed"), ("thermo1", "location.x")]) == ["0.5", "0"]

        stream = s.listen("thermo1", "data", marks=True)
        got = []
        async with asyncio.timeout(10):
            async for item in stream:
                got.append(item)
                if item is SYNC:
                    break
        await stream.aclose()
        assert isinstance(got[0], Event)
        assert got[0].service == "thermo1"
        with pytest.raises(NotFound):
            async for _ in s.listen("scoutX", "location"):
                pass
        assert await s.get("scout2", "speed") == "0.5"
    with pytest.raises(Cancelled):
        await s.get("scout2", "speed")


def test_sync_client(demo_target: str) -> None:
    with Client(demo_target) as c:
        assert "scout2" in c.services()
        assert c.get_vector("scout2", "location").shape == (6,)
        c.set("scout2", "speed", 0.5)
        assert c.get_number("scout2", "speed") == 0.5
        with pytest.raises(NotFound):
            c.get("scout2", "nothing")
        with c.listen("scout2", "location") as events:
            first = next(events)
        assert (first.service, first.property, first.sequence) == ("scout2", "location", 1)
        assert next(events, None) is None, "a closed iterator yields nothing more"
        with c.session() as s:
            assert s.get("scout2", "speed") == "0.5"
            with pytest.raises(NotFound):
                s.get("scoutX", "speed")


async def test_unreachable_gateway() -> None:
    target = f"127.0.0.1:{free_port()}"
    async with AsyncClient(target, timeout=5) as c:
        with pytest.raises(GatewayUnreachable, match="cannot reach the gateway"):
            await c.get("scout1", "location")


async def test_session_and_listen_end_when_the_gateway_stops(gateway_process: Any) -> None:
    gw = gateway_process()
    async with AsyncClient(gw.address, timeout=5) as c, c.session() as s:
        assert await s.get("scout1", "location.x") == "0"
        stream = c.listen("thermo1", "data")
        first = await anext(stream)
        assert first.service == "thermo1"
        await asyncio.to_thread(gw.stop)
        # The stream ends (normally or with a status) instead of hanging.
        async with asyncio.timeout(20):
            with contextlib.suppress(PropertyServiceError):
                async for _ in stream:
                    pass
        with pytest.raises(PropertyServiceError):
            await s.get("scout1", "location.x")
        assert s.closed
