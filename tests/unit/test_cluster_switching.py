"""The cluster's router entry: calls reach its current target, Listens move to a new one with a gap."""

from __future__ import annotations

import asyncio

import pytest
from support.fake_backend import DictBackend
from support.waiting import wait_until

from gateway.cluster import SwitchingBackend
from services.kernel.backend import Change
from services.kernel.errors import Code, PropertyError


async def test_calls_reach_the_target_and_say_why_without_one() -> None:
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001", reason="bot has no owner yet")
    with pytest.raises(PropertyError) as refused:
        await switching.get("x")
    assert refused.value.code is Code.UNAVAILABLE
    assert "bot has no owner yet" in refused.value.message
    first = DictBackend({"x": "1"}, type="sensor")
    await switching.switch(first, "owned here")
    assert await switching.get("x") == "1"
    assert await switching.set("x", "2") == "2"
    assert first.values["x"] == "2"
    assert switching.info.type == "sensor"
    assert switching.info.url == "tcp://127.0.0.1:7001"
    await switching.switch(None, reason="its owner left")
    with pytest.raises(PropertyError, match="its owner left"):
        await switching.get("x")
    assert first.closed


async def test_a_listen_moves_to_the_new_target_with_a_gap_and_the_current_value() -> None:
    first = DictBackend({"x": "1"})
    second = DictBackend({"x": "7"})
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(first, "forwarded to gw-a")
    heard: list[Change] = []
    sub, value = await switching.listen_current("x", heard.append)
    assert value == "1"
    first.put("x", "2")
    assert heard == [Change("x", "2")]
    await switching.switch(second, "forwarded to gw-b")
    await wait_until(lambda: len(heard) == 2, what="the gap event on the new target")
    assert heard[1] == Change("x", "7", gap=True)
    first.put("x", "3")  # the old target is closed and no longer heard
    second.put("x", "8")
    assert heard[2:] == [Change("x", "8")]
    assert first.closed and not first.subs
    await sub.close()
    assert not second.subs
    assert switching.listens == 0


async def test_a_listen_waits_without_a_target_and_resumes_when_one_comes() -> None:
    first = DictBackend({"x": "1"})
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(first, "forwarded to gw-a")
    heard: list[Change] = []
    await switching.listen("x", heard.append)
    await switching.switch(None, reason="owner gone")
    assert heard == []
    await asyncio.sleep(0.05)
    second = DictBackend({"x": "5"})
    await switching.switch(second, "owned here")
    await wait_until(lambda: heard == [Change("x", "5", gap=True)], what="the listen resumed with a gap")


async def test_a_new_target_that_cannot_be_reached_yet_is_tried_again() -> None:
    first = DictBackend({"x": "1"})
    second = DictBackend({"x": "4"}, unreachable=True)
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(first, "a")
    heard: list[Change] = []
    await switching.listen("x", heard.append)
    await switching.switch(second, "b")
    await asyncio.sleep(0.15)
    assert heard == []
    second.unreachable = False
    await wait_until(lambda: heard == [Change("x", "4", gap=True)], what="the retry on the new target")


async def test_a_property_the_new_target_lacks_is_reported_removed_once_it_had_time_to_catch_up() -> None:
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001", not_found_wait=0.3)
    await switching.switch(DictBackend({"x": "1"}), "a")
    heard: list[Change] = []
    await switching.listen("x", heard.append)
    began = asyncio.get_running_loop().time()
    await switching.switch(DictBackend({"y": "1"}), "b")
    await wait_until(lambda: heard == [Change("x", "", removed=True)], what="the removal")
    assert asyncio.get_running_loop().time() - began >= 0.3


async def test_a_new_target_that_finds_the_property_soon_is_a_move_not_a_removal() -> None:
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001", not_found_wait=5.0)
    await switching.switch(DictBackend({"x": "1"}), "a")
    heard: list[Change] = []
    await switching.listen("x", heard.append)
    late = DictBackend({"y": "1"})  # the new owner that has not caught up with the move yet
    await switching.switch(late, "b")
    await asyncio.sleep(0.15)
    late.values["x"] = "3"
    await wait_until(lambda: heard == [Change("x", "3", gap=True)], what="the move, with a gap")


async def test_a_gap_the_new_target_reports_for_the_same_move_is_not_told_twice() -> None:
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(DictBackend({"x": "1"}), "a")
    heard: list[Change] = []
    await switching.listen("x", heard.append)
    second = DictBackend({"x": "4"})
    await switching.switch(second, "forwarded to gw-b")
    await wait_until(lambda: heard == [Change("x", "4", gap=True)], what="the gap of the move")
    # gw-b was still connecting to the device when the listen reached it: it reports its own gap.
    second._notify(Change("x", "4", gap=True))
    second._notify(Change("x", "5", gap=True))
    second.put("x", "6")
    second._notify(Change("x", "7", gap=True))  # a later interruption is one of its own
    assert heard == [
        Change("x", "4", gap=True),
        Change("x", "5"),
        Change("x", "6"),
        Change("x", "7", gap=True),
    ]


async def test_closing_closes_the_target_and_every_listen() -> None:
    target = DictBackend({"x": "1"})
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(target, "a")
    await switching.listen("x", lambda change: None)
    await switching.aclose()
    assert target.closed and not target.subs
    late = DictBackend({"x": "1"})
    await switching.switch(late, "b")  # a switch after closing closes what it is handed
    assert late.closed


async def test_waiting_for_a_connection_waits_for_a_target() -> None:
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001", reason="nobody owns bot")
    with pytest.raises(PropertyError, match="nobody owns bot"):
        await switching.wait_connected(0.05)
    waiting = asyncio.ensure_future(switching.wait_connected(5.0))
    await asyncio.sleep(0.02)
    assert not waiting.done()
    await switching.switch(DictBackend({"x": "1"}, type="robot"), "a")
    await waiting
    assert switching.info.type == "robot"
