"""The listen hub without gRPC: a stream's conflating queue, batching, sync and release of topics."""

from __future__ import annotations

import pytest
from support.fake_backend import DictBackend

from gateway.config import Limits
from gateway.engine.events import Event, ListenRequest, Mark, Taken, events
from gateway.engine.listen import ListenHub, ListenStream, Selector, StreamOptions
from gateway.engine.listen.requests import check_listen
from gateway.engine.router import Router
from gateway.fronts.grpc_v1.listen_encoding import listen_wire
from services.kernel.errors import InvalidArgument, ResourceExhausted


@pytest.fixture
def hub() -> ListenHub:
    router = Router()
    router.add("s", DictBackend({"a": "1", "b": "2", "c": "3"}))
    return ListenHub(router, Limits(), call_timeout=1.0)


def drain(stream: ListenStream) -> list[Taken]:
    out = []
    while (taken := stream.take()) is not None:
        out.append(taken)
    return out


#: (path, value, sequence) of the current values a stream of s/* is sent first.
SENT = [("a", "1", 1), ("b", "2", 2), ("c", "3", 3)]


def values(taken: Taken) -> list[Event] | Mark:
    return taken if isinstance(taken, Mark) else events(taken)


async def test_current_values_then_sync_then_conflated_changes(hub: ListenHub) -> None:
    woken: list[int] = []
    stream = hub.open([Selector("s", "*")], StreamOptions(max_batch=2), lambda: woken.append(1))
    await stream.start()
    assert woken
    first = [values(taken) for taken in drain(stream)]
    assert len(first) == 3 and first[2] is Mark.SYNC  # max_batch=2: two responses of values, then sync
    one, two = first[0], first[1]
    assert isinstance(one, list) and isinstance(two, list) and len(one) == 2
    stamps = [e.time_ns for e in one + two]
    assert one + two == [Event("s", p, v, n, t) for (p, v, n), t in zip(SENT, stamps, strict=True)]
    store = hub.router.backend("s")
    assert isinstance(store, DictBackend)
    for i in range(100):
        store.put("b", str(i))
    (taken,) = drain(stream)
    assert [(e.path, e.value, e.conflated, e.sequence) for e in values(taken)] == [("b", "99", 99, 4)]
    assert len(store.subs) == 4  # a, b, c and the properties list
    stream.close()
    await hub.aclose()
    assert store.subs == []
    assert hub.topic_count == 0 and hub.stream_count == 0


async def test_topics_are_shared_between_streams(hub: ListenHub) -> None:
    streams = [hub.open([Selector("s", "a")], StreamOptions(), lambda: None) for _ in range(10)]
    for s in streams:
        await s.start()
    assert hub.topic_count == 1
    for s in streams:
        s.close()
    await hub.aclose()
    store = hub.router.backend("s")
    assert isinstance(store, DictBackend)
    assert store.subs == []


def test_selectors_and_options_are_checked() -> None:
    limits = Limits(max_selectors=2)
    selectors, _ = check_listen(ListenRequest([Selector("s", "a"), Selector("s", "b")]), limits)
    assert selectors == [Selector("s", "a"), Selector("s", "b")]
    assert check_listen(ListenRequest([Selector("s", "a")] * 2), limits)[0] == [Selector("s", "a")]  # once
    with pytest.raises(ResourceExhausted):
        check_listen(ListenRequest([Selector("s", "a")] * 3), limits)
    with pytest.raises(InvalidArgument):
        check_listen(ListenRequest([Selector("", "a")]), limits)
    with pytest.raises(InvalidArgument):
        check_listen(ListenRequest([Selector("s", "a*")]), limits)
    with pytest.raises(InvalidArgument, match="must not be negative"):
        check_listen(ListenRequest([Selector("s", "a")], heartbeat_interval=-1.0), limits)
    with pytest.raises(InvalidArgument, match="below the floor"):
        check_listen(
            ListenRequest([Selector("s", "a")], sample_interval=limits.min_interval_floor / 2), limits
        )
    _, options = check_listen(
        ListenRequest([Selector("s", "a")], min_interval=0.005, max_batch=100_000), limits
    )
    assert (options.min_interval, options.max_batch) == (0.005, limits.max_batch)


async def test_every_stream_a_change_reaches_takes_the_same_shared_event_encoded_once(hub: ListenHub) -> None:
    streams = [hub.open([Selector("s", "a")], StreamOptions(), lambda: None) for _ in range(3)]
    for stream in streams:
        await stream.start()
        drain(stream)  # the current value and sync
    store = hub.router.backend("s")
    assert isinstance(store, DictBackend)
    store.put("a", "changed")
    batches = [stream.take() for stream in streams]
    assert all(isinstance(batch, tuple) and len(batch[0]) == 1 for batch in batches)
    (event,) = {batch[0][0][1].value for batch in batches if isinstance(batch, tuple)}
    assert event.value == "changed" and event.encoded is None  # nothing encoded before a writer asks
    wires = [listen_wire(batch) for batch in batches if batch is not None]
    encoded = event.encoded
    assert encoded is not None and list(encoded.leads) == [2]  # one lead, made by the first stream
    assert wires[0] == wires[1] == wires[2]  # each its event number 2: the same bytes
    for stream in streams:
        stream.close()
    await hub.aclose()


async def test_a_topic_that_fails_to_open_after_its_listener_left_logs_no_unretrieved_error(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A Listen cancelled while its topic opens (the client went away), then the device's link
    closes: the opening's failure is handled (the topic is dropped), so asyncio has nothing to log."""
    import asyncio
    import gc

    from services.kernel.errors import Unavailable

    release = asyncio.Event()

    class ClosingLink(DictBackend):
        async def listen_current(self, path, notify, params=None):  # type: ignore[no-untyped-def,override]
            await release.wait()
            raise Unavailable("device d: proxy closed")

    router = Router()
    router.add("d", ClosingLink({"a": "1"}))
    hub = ListenHub(router, Limits(), call_timeout=5.0)
    stream = hub.open([Selector("d", "a")], StreamOptions(), lambda: None)
    starting = asyncio.create_task(stream.start())
    await asyncio.sleep(0.01)
    starting.cancel()
    with pytest.raises(asyncio.CancelledError):
        await starting
    stream.close()
    with caplog.at_level("ERROR", logger="asyncio"):
        release.set()
        for _ in range(5):
            await asyncio.sleep(0)
        await hub.aclose()
        del stream, starting
        gc.collect()
        await asyncio.sleep(0)
    assert "never retrieved" not in caplog.text, caplog.text
    assert hub.topic_count == 0
