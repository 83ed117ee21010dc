"""The listen hub without gRPC: a stream's conflating queue, batching, sync and release of topics."""

from __future__ import annotations

import pytest
from support.fake_backend import DictBackend

from gateway.config import Limits
from gateway.listen import ListenHub, Selector, StreamOptions, parse_options, parse_selectors
from gateway.router import Router
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.errors import InvalidArgument, ResourceExhausted


@pytest.fixture
def hub() -> ListenHub:
    router = Router()
    router.add("s", DictBackend({"a": "1", "b": "2", "c": "3"}))
    return ListenHub(router, Limits(), call_timeout=1.0)


def drain(stream) -> list[pb.ListenResponse]:
    out = []
    while (msg := stream.take()) is not None:
        out.append(msg)
    return out


async def test_current_values_then_sync_then_conflated_changes(hub: ListenHub) -> None:
    woken: list[int] = []
    stream = hub.open([Selector("s", "*")], StreamOptions(max_batch=2), lambda: woken.append(1))
    await stream.start()
    assert woken
    first = drain(stream)
    assert [[e.value for e in m.events] for m in first] == [["1", "2"], ["3"], []]
    assert first[-1].sync
    store = hub.router.backend("s")
    assert isinstance(store, DictBackend)
    for i in range(100):
        store.put("b", str(i))
    (msg,) = drain(stream)
    assert [(e.property, e.value, e.conflated, e.sequence) for e in msg.events] == [("b", "99", 99, 4)]
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
    request = pb.ListenRequest(service="s", property="a", more=[pb.PropertyRef(property="b")])
    assert parse_selectors(request, limits) == [Selector("s", "a"), Selector("s", "b")]
    with pytest.raises(ResourceExhausted):
        parse_selectors(pb.ListenRequest(service="s", property="a", more=[pb.PropertyRef()] * 2), limits)
    with pytest.raises(InvalidArgument):
        parse_selectors(pb.ListenRequest(service="", property="a"), limits)
    with pytest.raises(InvalidArgument):
        parse_selectors(pb.ListenRequest(service="s", property="a*"), limits)
    opts = pb.ListenOptions(max_batch=100_000)
    opts.min_interval.FromMilliseconds(5)
    parsed = parse_options(opts, limits)
    assert (parsed.min_interval, parsed.max_batch) == (0.005, limits.max_batch)
