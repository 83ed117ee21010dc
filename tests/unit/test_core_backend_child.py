"""A child namespace that is a Backend (a group's member): its metadata, as ``psctl ls -l`` asks for it,
and its property list, followed again once a child that was away answers."""

from __future__ import annotations

import asyncio

import pytest
from support.fake_backend import DictBackend
from support.waiting import wait_until

from services.apps.simulators import SimRobot
from services.kernel.backend import Backend, Change
from services.kernel.core import LocalService, Resource
from services.kernel.core import local as local_module
from services.kernel.values import parse_names


class Holder(Resource):
    """Holds one robot behind its Backend, as a group holds its members."""

    def __init__(self) -> None:
        self.attach("bot", LocalService(SimRobot()))


async def test_meta_of_a_backend_child_namespace() -> None:
    service = LocalService(Holder())
    await service.start()
    try:
        assert await service.get("bot.gui") == "group"
        assert await service.get("bot.parameters") == "()"
        assert await service.get("bot.doc") == ""
        # Below the namespace the child answers for itself.
        assert await service.get("bot.location.gui") == "pose"
        assert await service.get("bot.behaviors.moveto.parameters") == "((frame text world))"
    finally:
        await service.aclose()


class Keeper(Resource):
    """Holds one Backend child that the test can cut off, as a group holds a member device."""

    def __init__(self, child: Backend) -> None:
        self.attach("member", child)


def list_retries() -> list[asyncio.Task[object]]:
    return [
        t
        for t in asyncio.all_tasks()
        if not t.done()
        and getattr(t.get_coro(), "__qualname__", "") == "LocalService._follow_remote_list_later"
    ]


async def test_the_list_of_a_child_that_was_away_is_followed_once_it_answers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(local_module, "REMOTE_LIST_RETRY_FIRST_S", 0.01)
    monkeypatch.setattr(local_module, "REMOTE_LIST_RETRY_MAX_S", 0.05)
    member = DictBackend({"x": "1"}, unreachable=True)
    service = LocalService(Keeper(member))
    await service.start()
    changes: list[Change] = []
    sub = await service.listen("properties", changes.append)
    try:
        assert "member.x" not in await service.properties()
        assert len(list_retries()) == 1
        member.unreachable = False
        await wait_until(lambda: bool(changes), what="the listing changes once the child answers")
        assert "member.x" in parse_names(changes[-1].value) and changes[-1].gap
        assert list_retries() == []
        # Followed from then on: a property the child adds shows in the listing.
        member.add("y", "2")
        await wait_until(lambda: "member.y" in parse_names(changes[-1].value), what="the new name")
        assert not changes[-1].gap
    finally:
        await sub.close()
        await service.aclose()


async def test_asking_a_child_that_is_away_stops_when_nobody_listens_to_the_list(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(local_module, "REMOTE_LIST_RETRY_FIRST_S", 0.01)
    monkeypatch.setattr(local_module, "REMOTE_LIST_RETRY_MAX_S", 0.05)
    service = LocalService(Keeper(DictBackend({"x": "1"}, unreachable=True)))
    await service.start()
    sub = await service.listen("properties", lambda change: None)
    assert len(list_retries()) == 1
    await sub.close()
    await wait_until(lambda: list_retries() == [], what="the retry ends with the last listener")
    await service.aclose()
