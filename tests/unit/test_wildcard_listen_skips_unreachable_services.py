"""The listen hub without gRPC: a wildcard skips what cannot be reached, tries it again, and stops trying.

Services are :class:`~support.fake_backend.DictBackend`s whose link the test cuts and mends.
The pauses between tries are shortened here (the real ones are 0.5 s doubling to 10 s, which
:func:`gateway.engine.listen.stream.retry_pauses` shows).
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator, Mapping
from itertools import islice

import pytest
from support.fake_backend import DictBackend
from support.hub_reader import Reader
from support.waiting import wait_until

from gateway.config import Limits
from gateway.engine.listen import ListenHub, Selector, StreamOptions
from gateway.engine.listen import stream as stream_module
from gateway.engine.router import Router
from services.kernel.backend import NO_PARAMS, Notify, Subscription
from services.kernel.backoff import pauses
from services.kernel.errors import Code, PropertyError, ResourceExhausted, Unavailable


@pytest.fixture(autouse=True)
def quick_retries(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(stream_module, "RETRY_FIRST_S", 0.01)
    monkeypatch.setattr(stream_module, "RETRY_MAX_S", 0.05)


def running(qualname: str) -> list[asyncio.Task[object]]:
    """The tasks alive in this event loop that run the coroutine ``qualname``."""
    tasks = [t for t in asyncio.all_tasks() if not t.done()]
    return [t for t in tasks if getattr(t.get_coro(), "__qualname__", "") == qualname]


def retry_tasks() -> list[asyncio.Task[object]]:
    """The stream retry tasks alive in this event loop."""
    return running("ListenStream._retry")


@pytest.fixture
def router() -> Router:
    router = Router()
    router.add("up", DictBackend({"a": "1", "b": "2"}))
    router.add("down", DictBackend({"a": "10", "b": "20"}, unreachable=True))
    return router


@pytest.fixture
def hub(router: Router) -> ListenHub:
    return ListenHub(router, Limits(), call_timeout=0.2)


def dict_backend(router: Router, name: str) -> DictBackend:
    backend = router.lookup(name)
    assert isinstance(backend, DictBackend)
    return backend


async def test_a_wildcard_service_skips_an_unreachable_one_and_follows_it_once_back(
    hub: ListenHub, router: Router
) -> None:
    reader = Reader(hub, Selector("*", "a"))
    await reader.start()
    assert reader.events == [("up", "a", "1", False)]
    assert reader.stream.retrying == 1 and reader.stream.error is None
    down = dict_backend(router, "down")
    down.unreachable = False
    await reader.until(("down", "a", "10", True))
    await wait_until(lambda: reader.stream.retrying == 0, what="the retry ends once the service answers")
    down.put("a", "11")
    await reader.until(("down", "a", "11", False))
    assert retry_tasks() == []
    reader.stream.close()
    await hub.aclose()


async def test_a_wildcard_path_skips_an_unreachable_service_and_lists_it_once_back(
    hub: ListenHub, router: Router
) -> None:
    reader = Reader(hub, Selector("down", "*"), Selector("up", "*"))
    await reader.start()
    assert sorted(reader.events) == [("up", "a", "1", False), ("up", "b", "2", False)]
    dict_backend(router, "down").unreachable = False
    await reader.until(("down", "a", "10", True))
    await reader.until(("down", "b", "20", True))
    # Followed from then on, property list included.
    dict_backend(router, "down").add("c", "30")
    await reader.until(("down", "c", "30", False))
    reader.stream.close()
    await hub.aclose()


async def test_an_exact_selector_on_an_unreachable_service_fails_with_unavailable(hub: ListenHub) -> None:
    reader = Reader(hub, Selector("up", "a"), Selector("down", "a"))
    with pytest.raises(Unavailable):
        await reader.stream.start()
    reader.stream.close()
    assert retry_tasks() == []
    await hub.aclose()


async def test_a_service_too_slow_to_answer_is_skipped_like_an_unreachable_one(
    hub: ListenHub, router: Router
) -> None:
    slow = DictBackend({"a": "slow"}, delay=5.0)  # far beyond the hub's call timeout of 0.2 s
    router.add("slow", slow)
    reader = Reader(hub, Selector("*", "a"))
    await reader.start()
    assert ("slow", "a", "slow", False) not in reader.events and reader.stream.retrying == 2
    slow.delay = 0.0
    await reader.until(("slow", "a", "slow", True))
    reader.stream.close()
    await hub.aclose()


async def test_a_service_that_joins_unreachable_does_not_end_the_stream(
    hub: ListenHub, router: Router
) -> None:
    reader = Reader(hub, Selector("*", "b"))
    await reader.start()
    late = DictBackend({"b": "late"}, unreachable=True)
    router.add("late", late)
    await wait_until(lambda: reader.stream.retrying == 2, what="the joining service is tried again")
    assert reader.stream.error is None
    late.unreachable = False
    await reader.until(("late", "b", "late", True))
    reader.stream.close()
    await hub.aclose()


class PartlyReachable(DictBackend):
    """A service that lists every property but cannot reach some (a group whose member is away)."""

    def __init__(self, values: Mapping[str, str], cut: set[str]) -> None:
        super().__init__(values)
        self.cut = cut

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path in self.cut:
            raise Unavailable(f"the member behind {path} is not connected")
        return await super().listen(path, notify, params)


async def test_a_property_that_cannot_be_reached_is_skipped_alone(hub: ListenHub, router: Router) -> None:
    group = PartlyReachable({"m1.x": "1", "m2.x": "2", "m3.x": "3"}, cut={"m2.x"})
    router.add("group", group)
    reader = Reader(hub, Selector("group", "*.x"))
    await reader.start()
    assert reader.events == [("group", "m1.x", "1", False), ("group", "m3.x", "3", False)]
    assert reader.stream.retrying == 1
    group.cut.clear()
    await reader.until(("group", "m2.x", "2", True))
    group.put("m2.x", "22")
    await reader.until(("group", "m2.x", "22", False))
    reader.stream.close()
    await hub.aclose()


async def test_the_retry_task_ends_when_the_stream_closes(hub: ListenHub) -> None:
    reader = Reader(hub, Selector("*", "a"), Selector("*", "b"))
    await reader.start()
    # One task per (selector, service) skipped, however many tries it has made.
    await asyncio.sleep(0.2)
    assert len(retry_tasks()) == reader.stream.retrying == 2
    reader.stream.close()
    await wait_until(lambda: retry_tasks() == [], what="the retry tasks end with the stream")
    assert reader.stream.retrying == 0
    await hub.aclose()


async def test_the_retry_task_ends_when_the_service_leaves_the_router(hub: ListenHub, router: Router) -> None:
    reader = Reader(hub, Selector("*", "a"))
    await reader.start()
    assert len(retry_tasks()) == 1
    router.remove("down")
    await wait_until(lambda: retry_tasks() == [], what="the retry task ends with the service")
    assert reader.stream.retrying == 0 and reader.stream.error is None
    reader.stream.close()
    await hub.aclose()


async def test_updates_only_still_gets_the_value_of_a_service_that_is_back(
    hub: ListenHub, router: Router
) -> None:
    reader = Reader(hub, Selector("*", "a"), options=StreamOptions(updates_only=True))
    await reader.start()
    assert reader.events == []
    dict_backend(router, "down").unreachable = False
    await reader.until(("down", "a", "10", True))
    reader.stream.close()
    await hub.aclose()


def test_the_pauses_double_from_half_a_second_up_to_ten(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.undo()  # the real pauses
    pauses: Iterator[float] = stream_module.retry_pauses()
    assert list(islice(pauses, 8)) == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0, 10.0]


class Refusing(DictBackend):
    """A service that refuses every Listen for a reason other than reach."""

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        raise ResourceExhausted("the device holds no more listens")


async def test_a_wildcard_still_fails_on_an_error_that_is_not_about_reach(
    hub: ListenHub, router: Router
) -> None:
    router.add("full", Refusing({"a": "x"}))
    reader = Reader(hub, Selector("*", "a"))
    with pytest.raises(PropertyError) as info:
        await reader.stream.start()
    assert info.value.code == Code.RESOURCE_EXHAUSTED
    reader.stream.close()  # the skipped "down" was being tried again: that ends too
    await wait_until(lambda: retry_tasks() == [], what="the retry task ends with the stream")
    await hub.aclose()


async def test_an_exact_selector_waits_a_while_for_its_service_to_come_back_connecting(
    hub: ListenHub, router: Router
) -> None:
    reader = Reader(hub, Selector("up", "a"))
    await reader.start()
    router.remove("up")
    again = DictBackend({"a": "again"}, unreachable=True)  # registered again, its proxy still connecting
    router.add("up", again)
    await wait_until(lambda: reader.stream.retrying == 1, what="the named service is tried again")
    again.unreachable = False
    await reader.until(("up", "a", "again", True))
    assert reader.stream.error is None
    reader.stream.close()
    await hub.aclose()


async def test_an_exact_selector_fails_when_its_service_comes_back_but_never_answers(
    hub: ListenHub, router: Router, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(stream_module, "JOIN_RETRY_S", 0.1)
    reader = Reader(hub, Selector("up", "a"))
    await reader.start()
    router.remove("up")
    router.add("up", DictBackend({"a": "again"}, unreachable=True))
    await wait_until(lambda: reader.stream.error is not None, what="the stream fails")
    assert reader.stream.error is not None and reader.stream.error.code == Code.UNAVAILABLE
    reader.stream.close()
    await wait_until(lambda: retry_tasks() == [], what="no retry is left")
    await hub.aclose()


async def test_an_exact_selector_whose_service_comes_back_without_the_property_stays_open(
    hub: ListenHub, router: Router
) -> None:
    reader = Reader(hub, Selector("up", "a"))
    await reader.start()
    router.remove("up")
    again = Asked({"b": "no a here"})
    router.add("up", again)
    await wait_until(
        lambda: "a" in again.asked and not running("ListenStream._expand_later"),
        what="the stream has asked the service that joined again",
    )
    await wait_until(lambda: ("up", "a", "", False) in reader.events, what="the removal")
    assert reader.stream.error is None and reader.stream.retrying == 0
    reader.stream.close()
    await hub.aclose()


class Asked(DictBackend):
    """Remembers which paths were asked to be listened to (after the answer is decided)."""

    def __init__(self, values: Mapping[str, str]) -> None:
        super().__init__(values)
        self.asked: list[str] = []

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        try:
            return await super().listen(path, notify, params)
        finally:
            self.asked.append(path)


class Connecting(DictBackend):
    """A proxy-like service: unreachable until the test connects it, and says when it is connected."""

    def __init__(self, values: Mapping[str, str]) -> None:
        super().__init__(values, unreachable=True)
        self.link = asyncio.Event()

    def connect(self) -> None:
        self.unreachable = False
        self.link.set()

    async def wait_connected(self, wait_s: float) -> None:
        try:
            async with asyncio.timeout(wait_s):
                await self.link.wait()
        except TimeoutError:
            raise Unavailable(f"not connected after {wait_s} s") from None


async def test_a_proxy_that_connects_again_is_tried_at_once_not_at_the_end_of_the_pause(
    hub: ListenHub, router: Router, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(stream_module, "RETRY_FIRST_S", 600.0)  # far beyond any wait of this test
    monkeypatch.setattr(stream_module, "RETRY_MAX_S", 600.0)
    device = Connecting({"a": "back"})
    router.add("device", device)
    reader = Reader(hub, Selector("*", "a"))
    await reader.start()
    assert ("device", "a", "back", True) not in reader.events and reader.stream.retrying == 2
    device.connect()
    await reader.until(("device", "a", "back", True))
    reader.stream.close()
    await hub.aclose()


def test_backoff_pauses_refuse_a_shape_that_would_not_pause() -> None:
    with pytest.raises(ValueError, match="first <= longest"):
        next(pauses(0.0, 10.0))
    with pytest.raises(ValueError, match="first <= longest"):
        next(pauses(20.0, 10.0))
