"""The gateway's follow (``gateway.engine.listen.follow.HubFollow``), the recorder's event source, on a
real listen hub in one process: the current values, then changes, as a Listen hears them; for a
caller, only what that caller may read; as a service's own work, everything; closed, nothing."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Annotated

import pytest
from support.waiting import wait_until

from gateway.config import Limits
from gateway.engine.guard import Guard
from gateway.engine.listen import ListenHub
from gateway.engine.listen.follow import HubFollow
from gateway.engine.router import Router
from gateway.engine.rules import Rule, Rules, Subject
from services.kernel.core import Prop, Resource, serve
from services.kernel.directory import CALLER
from services.kernel.errors import InvalidArgument, PermissionDenied
from services.kernel.follow import FollowedEvent

VIEWER = Subject("viewer", authenticated=True, via="token")


class Dial(Resource):
    """Two readings, set by the test."""

    resource_type = "dial"

    level: Annotated[float, Prop(readonly=True, doc="a reading")] = 1.5
    secret: Annotated[float, Prop(readonly=True, doc="another")] = 7.5


@pytest.fixture
async def hub() -> AsyncIterator[tuple[ListenHub, Dial]]:
    guard = Guard(
        Rules(
            [
                Rule.build(
                    0, subject="viewer", service="dial", path="level", operations=["read"], effect="permit"
                )
            ]
        )
    )
    router = Router(guard)
    dial = Dial()
    backend = serve(dial)
    await backend.start()
    router.add("dial", backend)
    listen_hub = ListenHub(router, Limits(), 5.0, guard)
    yield listen_hub, dial
    await listen_hub.aclose()
    await backend.aclose()


def values(heard: list[FollowedEvent]) -> list[tuple[str, str]]:
    return [(e.path, str(e.value)) for e in heard]


async def test_a_follow_hears_the_current_values_then_each_change_until_it_is_closed(
    hub: tuple[ListenHub, Dial],
) -> None:
    listen_hub, dial = hub
    heard: list[FollowedEvent] = []
    subscription = await HubFollow(listen_hub)(["dial/*"], heard.extend)  # no caller: own work
    await wait_until(lambda: len(heard) == 2, what="the current values")
    assert sorted(values(heard)) == [("level", "1.5"), ("secret", "7.5")]
    dial.level = 2.5
    await wait_until(lambda: len(heard) == 3, what="the change")
    assert values(heard)[2] == ("level", "2.5")
    assert [e.sequence for e in heard] == [1, 2, 3]
    assert heard[2].time_ns > 0 and not heard[2].gap
    await subscription.close()
    assert listen_hub.stream_count == 0
    dial.level = 3.5
    await asyncio.sleep(0.05)  # a change would reach a live follow within a loop turn or two
    assert len(heard) == 3


async def test_a_follow_opened_for_a_caller_hears_only_what_it_may_read(hub: tuple[ListenHub, Dial]) -> None:
    listen_hub, dial = hub
    follow = HubFollow(listen_hub)
    heard: list[FollowedEvent] = []
    token = CALLER.set(VIEWER)
    try:
        with pytest.raises(PermissionDenied):
            await follow(["dial/secret"], heard.extend)
        subscription = await follow(["dial/*"], heard.extend)
    finally:
        CALLER.reset(token)
    await wait_until(lambda: len(heard) == 1, what="the current value it may read")
    dial.secret = 8.5
    dial.level = 4.5
    await wait_until(lambda: len(heard) == 2, what="the change it may read")
    assert values(heard) == [("level", "1.5"), ("level", "4.5")]
    await subscription.close()
    assert listen_hub.stream_count == 0


async def test_a_bad_selector_is_refused_before_anything_opens(hub: tuple[ListenHub, Dial]) -> None:
    listen_hub, _ = hub
    with pytest.raises(InvalidArgument, match="SERVICE/PATH"):
        await HubFollow(listen_hub)(["location"], lambda events: None)
    assert listen_hub.stream_count == 0
