"""A device that dialled in goes to another gateway of the cluster when its own is gone."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest
from support.fake_backend import DictBackend
from support.waiting import wait_until

from gateway.engine.router import Router
from gateway.fronts.line.listener import LineListener
from services.device import DeviceServer
from services.device.alternates import GatewayAddresses, format_alternates, parse_alternates


def test_the_field_names_host_port_pairs() -> None:
    assert format_alternates(["127.0.0.1:7101", "", "[::1]:7102"]) == "127.0.0.1:7101,[::1]:7102"
    assert parse_alternates("127.0.0.1:7101,[::1]:7102,nonsense,host:0,host:99999,h:7") == [
        ("127.0.0.1", 7101),
        ("::1", 7102),
        ("h", 7),
    ]


def test_the_gateways_are_dialled_in_turn() -> None:
    gateways = GatewayAddresses(("a", 1))
    assert gateways.take() == (("a", 1), True)
    assert gateways.take() == (("a", 1), True)  # only one known: every attempt is a new round
    gateways.connected(("a", 1), "b:2,c:3")
    # After a drop: the other gateways first, then a new round from the one it was on.
    assert [gateways.take() for _ in range(4)] == [
        (("b", 2), False),
        (("c", 3), False),
        (("a", 1), True),
        (("b", 2), False),
    ]
    gateways.connected(("c", 3), "a:1,b:2")
    assert gateways.addresses == [("c", 3), ("a", 1), ("b", 2)]


def test_a_pause_is_due_once_every_gateway_was_dialled_whatever_the_greetings_said() -> None:
    gateways = GatewayAddresses(("a", 1))
    assert not gateways.pause_due()  # the first attempt goes at once
    gateways.take()
    gateways.connected(("a", 1), "b:2,c:3")  # a greets, then refuses
    assert gateways.pause_due() is False
    for _ in range(2):
        address, _ = gateways.take()
        gateways.connected(address, "a:1,b:2,c:3")  # each greets (starting the turn again), refuses
    assert gateways.pause_due()
    gateways.rested()
    assert not gateways.pause_due()


@pytest.fixture
async def two_listeners() -> AsyncIterator[tuple[tuple[Router, LineListener], tuple[Router, LineListener]]]:
    first, second = Router(), Router()
    addresses: dict[str, str] = {}
    listener_a = LineListener(first, alternates=lambda: [addresses["b"]])
    listener_b = LineListener(second, alternates=lambda: [addresses["a"]])
    host, port = await listener_a.start("127.0.0.1", 0)
    addresses["a"] = f"{host}:{port}"
    host, port = await listener_b.start("127.0.0.1", 0)
    addresses["b"] = f"{host}:{port}"
    yield (first, listener_a), (second, listener_b)
    for router, listener in ((first, listener_a), (second, listener_b)):
        await listener.aclose()
        for name in router.names():
            await router.remove(name).aclose()


async def test_a_device_whose_gateway_is_gone_dials_the_alternate_it_was_told(
    two_listeners: tuple[tuple[Router, LineListener], tuple[Router, LineListener]],
) -> None:
    (first, listener_a), (second, _listener_b) = two_listeners
    device = DeviceServer(DictBackend({"x": "1"}, type="sensor"), name="probe")
    assert listener_a.address is not None
    dialling = asyncio.ensure_future(device.dial(*listener_a.address, retry_initial=0.05, retry_max=0.5))
    try:
        await wait_until(lambda: "probe" in first, what="the device registered on its first gateway")
        assert await first.lookup("probe").get("x") == "1"
        await listener_a.aclose()  # the first gateway is gone
        await first.remove("probe").aclose()
        await wait_until(lambda: "probe" in second, what="the device registered on the alternate")
        assert await second.lookup("probe").get("x") == "1"
    finally:
        dialling.cancel()
        await asyncio.gather(dialling, return_exceptions=True)
        await device.aclose()


async def test_a_device_refused_by_every_gateway_pauses_between_rounds(
    two_listeners: tuple[tuple[Router, LineListener], tuple[Router, LineListener]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Each gateway greets (naming the other) and then refuses the name: a round of both, then a pause."""
    (first, listener_a), (second, _listener_b) = two_listeners
    for router in (first, second):
        router.add("probe", DictBackend({"x": "0"}, url="tcp://127.0.0.1:9"))  # the name is taken
    device = DeviceServer(DictBackend({"x": "1"}, type="sensor"), name="probe")
    assert listener_a.address is not None
    caplog.set_level("WARNING", logger="gateway.fronts.line.listener")
    dialling = asyncio.ensure_future(device.dial(*listener_a.address, retry_initial=0.2, retry_max=0.4))
    try:
        await asyncio.sleep(1.0)
    finally:
        dialling.cancel()
        await asyncio.gather(dialling, return_exceptions=True)
        await device.aclose()
    refusals = [r for r in caplog.records if "is taken" in r.getMessage()]
    # Rounds of two at 0, 0.2, 0.6 s (pauses 0.2, 0.4): 6 refusals in a second, not hundreds.
    assert 2 <= len(refusals) <= 8, f"{len(refusals)} refusals in 1 s"
