"""The listen hub through a real gRPC server in this process, over a service the test controls."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import grpc
import pytest
from google.protobuf.duration_pb2 import Duration
from support.fake_backend import DictBackend
from support.waiting import wait_until

from gateway.app import Gateway
from gateway.config import Config, GatewaySection, Limits
from gateway.testing import running_gateway
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 5.0


def config(**limits: int) -> Config:
    return Config(gateway=GatewaySection(call_timeout=1.0), limits=Limits(**limits))


@pytest.fixture
def dev() -> DictBackend:
    return DictBackend({"a": "1", "b": "2", "arm.x": "0", "arm.y": "0", "ro": "fixed"}, readonly=("ro",))


@pytest.fixture
async def stub(dev: DictBackend) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with (
        running_gateway(dev, name="dev", config=config()) as gw,
        grpc.aio.insecure_channel(gw.address) as channel,
    ):
        s = pb_grpc.PropertyServiceStub(channel)
        s.gateway = gw
        yield s


async def read(call: grpc.aio.UnaryStreamCall, limit: float = WAIT) -> pb.ListenResponse:
    return await asyncio.wait_for(call.read(), limit)


async def events_until_sync(call: grpc.aio.UnaryStreamCall) -> list[pb.Event]:
    events: list[pb.Event] = []
    while True:
        msg = await read(call)
        events.extend(msg.events)
        if msg.sync:
            return events


def seconds(s: float) -> Duration:
    d = Duration()
    d.FromNanoseconds(int(s * 1e9))
    return d


async def test_current_values_then_sync_then_changes(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="a", more=[pb.PropertyRef(property="b")]))
    first = await events_until_sync(call)
    assert [(e.property, e.value, e.sequence) for e in first] == [("a", "1", 1), ("b", "2", 2)]
    dev.put("a", "10")
    msg = await read(call)
    assert [(e.service, e.property, e.value, e.sequence, e.conflated) for e in msg.events] == [
        ("dev", "a", "10", 3, 0)
    ]
    assert msg.events[0].time.seconds > 0
    call.cancel()


async def test_burst_is_conflated_with_a_count(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="a"))
    await events_until_sync(call)
    for i in range(1000):
        dev.put("a", str(i))
    msg = await read(call)
    assert [(e.value, e.conflated) for e in msg.events] == [("999", 999)]
    call.cancel()


async def test_slow_reader_memory_is_bounded_by_properties(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="*"))
    await events_until_sync(call)
    # Flood far beyond what flow control absorbs, never reading, yielding to the writer now and then.
    for i in range(20_000):
        dev.put("a", f"{i:0200d}")
        dev.put("b", str(i))
        if i % 100 == 0:
            await asyncio.sleep(0)
    (stream,) = stub.gateway.hub._streams
    assert len(stream._pending) <= 5
    last: dict[str, pb.Event] = {}
    conflated = 0
    while last.get("b", pb.Event()).value != "19999":
        for e in (await read(call)).events:
            last[e.property] = e
            conflated += e.conflated
    assert last["a"].value == f"{19999:0200d}"
    assert conflated > 0
    call.cancel()


async def test_sequence_numbers_have_no_holes(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="*", options=pb.ListenOptions(max_batch=2)))
    seqs = [e.sequence for e in await events_until_sync(call)]
    for i in range(50):
        dev.put("a", str(i))
        dev.put("b", str(i))
        await asyncio.sleep(0)
    while True:
        msg = await read(call)
        assert len(msg.events) <= 2
        seqs += [e.sequence for e in msg.events]
        if msg.events and msg.events[-1].property == "b" and msg.events[-1].value == "49":
            break
    assert seqs == list(range(1, len(seqs) + 1))
    call.cancel()


async def test_one_backend_subscription_shared_and_released(stub, dev) -> None:
    calls = [stub.Listen(pb.ListenRequest(service="dev", property="a")) for _ in range(3)]
    for c in calls:
        await events_until_sync(c)
    assert dev.listeners("a") == 1
    calls[0].cancel()
    dev.put("a", "x")
    for c in calls[1:]:
        assert (await read(c)).events[0].value == "x"
    for c in calls[1:]:
        c.cancel()
    await wait_until(lambda: dev.listeners("a") == 0)
    assert stub.gateway.hub.topic_count == 0
    assert stub.gateway.hub.stream_count == 0


async def test_vanished_client_does_not_disturb_another(dev) -> None:
    async with running_gateway(dev, name="dev", config=config()) as gw:
        stay = grpc.aio.insecure_channel(gw.address)
        gone = grpc.aio.insecure_channel(gw.address)
        a = pb_grpc.PropertyServiceStub(stay).Listen(pb.ListenRequest(service="dev", property="a"))
        b = pb_grpc.PropertyServiceStub(gone).Listen(pb.ListenRequest(service="dev", property="*"))
        await events_until_sync(a)
        await events_until_sync(b)
        await gone.close(grace=None)  # the connection goes away mid-stream
        await wait_until(lambda: gw.hub.stream_count == 1)
        dev.put("a", "still here")
        assert (await read(a)).events[0].value == "still here"
        await wait_until(lambda: dev.listeners("b") == 0 and dev.listeners("properties") == 0)
        assert dev.listeners("a") == 1
        await stay.close()


async def test_wildcard_path_follows_the_property_list(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="arm.*"))
    first = await events_until_sync(call)
    assert sorted(e.property for e in first) == ["arm.x", "arm.y"]
    dev.add("arm.z", "5")
    msg = await read(call)
    assert [(e.property, e.value, e.removed) for e in msg.events] == [("arm.z", "5", False)]
    dev.remove("arm.x")
    msg = await read(call)
    assert [(e.property, e.value, e.removed) for e in msg.events] == [("arm.x", "", True)]
    dev.put("arm.z", "6")
    assert (await read(call)).events[0].value == "6"
    call.cancel()


async def test_updates_only_sends_a_property_that_appears_later(stub, dev) -> None:
    """Only changes, and a property coming into being is one: its first value is sent."""
    opts = pb.ListenOptions(updates_only=True)
    call = stub.Listen(pb.ListenRequest(service="dev", property="arm.*", options=opts))
    msg = await read(call)
    assert msg.sync and not msg.events
    dev.add("arm.z", "5")
    msg = await read(call)
    assert [(e.property, e.value, e.removed) for e in msg.events] == [("arm.z", "5", False)]
    dev.remove("arm.z")
    msg = await read(call)
    assert [(e.property, e.value, e.removed) for e in msg.events] == [("arm.z", "", True)]
    call.cancel()


async def test_wildcard_service_follows_services_coming_and_going(stub, dev) -> None:
    gw: Gateway = stub.gateway
    call = stub.Listen(pb.ListenRequest(service="*", property="a"))
    first = await events_until_sync(call)
    assert [(e.service, e.value) for e in first] == [("dev", "1")]
    other = DictBackend({"a": "other"})
    gw.router.add("dev2", other)
    msg = await read(call)
    assert [(e.service, e.property, e.value) for e in msg.events] == [("dev2", "a", "other")]
    gw.router.remove("dev2")
    msg = await read(call)
    assert [(e.service, e.removed) for e in msg.events] == [("dev2", True)]
    call.cancel()


async def test_wildcard_matching_nothing_waits_for_matches(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="tool.*"))
    msg = await read(call)
    assert msg.sync and not msg.events
    dev.add("tool.grip", "open")
    assert (await read(call)).events[0].property == "tool.grip"
    call.cancel()


async def test_unknown_concrete_path_is_not_found_before_streaming(stub) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="nope"))
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await read(call)
    assert err.value.code() == grpc.StatusCode.NOT_FOUND
    call = stub.Listen(pb.ListenRequest(service="nodev", property="a"))
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await read(call)
    assert err.value.code() == grpc.StatusCode.NOT_FOUND
    assert "dev" in err.value.details()


async def test_updates_only_sends_sync_first(stub, dev) -> None:
    call = stub.Listen(
        pb.ListenRequest(service="dev", property="a", options=pb.ListenOptions(updates_only=True))
    )
    msg = await read(call)
    assert msg.sync and not msg.events
    dev.put("a", "new")
    assert [e.value for e in (await read(call)).events] == ["new"]
    call.cancel()


async def test_min_interval_throttles_and_counts(stub, dev) -> None:
    opts = pb.ListenOptions(min_interval=seconds(0.2))
    call = stub.Listen(pb.ListenRequest(service="dev", property="a", options=opts))
    await events_until_sync(call)
    dev.put("a", "x1")
    first = (await read(call)).events
    assert [e.value for e in first] == ["x1"]
    for i in range(5):
        dev.put("a", f"y{i}")
        await asyncio.sleep(0.01)
    second = (await read(call)).events
    assert [(e.value, e.conflated) for e in second] == [("y4", 4)]
    gap = (second[0].time.ToNanoseconds() - first[0].time.ToNanoseconds()) / 1e9
    assert gap >= 0.0  # both stamped when seen; the throttle delays sending, not seeing
    call.cancel()


async def test_sample_interval_repeats_unchanged_values(stub, dev) -> None:
    opts = pb.ListenOptions(sample_interval=seconds(0.05))
    call = stub.Listen(pb.ListenRequest(service="dev", property="a", options=opts))
    await events_until_sync(call)
    samples = [(await read(call)).events[0].value for _ in range(3)]
    assert samples == ["1", "1", "1"]
    call.cancel()


async def test_heartbeat_on_a_quiet_stream(stub) -> None:
    opts = pb.ListenOptions(heartbeat_interval=seconds(0.05))
    call = stub.Listen(pb.ListenRequest(service="dev", property="a", options=opts))
    await events_until_sync(call)
    msg = await read(call)
    assert msg.heartbeat and not msg.events
    call.cancel()


@pytest.mark.parametrize("field", ["min_interval", "sample_interval", "heartbeat_interval"])
async def test_interval_below_the_floor_is_invalid(stub, field) -> None:
    opts = pb.ListenOptions(**{field: Duration(nanos=1000)})
    call = stub.Listen(pb.ListenRequest(service="dev", property="a", options=opts))
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await read(call)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert field in err.value.details()


async def test_limits_are_resource_exhausted(dev) -> None:
    cfg = config(max_selectors=2, max_stream_properties=2, max_streams=1)
    async with (
        running_gateway(dev, name="dev", config=cfg) as gw,
        grpc.aio.insecure_channel(gw.address) as channel,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)
        many = [pb.PropertyRef(property=p) for p in ("a", "b")]
        for request in (
            pb.ListenRequest(service="dev", property="ro", more=many),
            pb.ListenRequest(service="dev", property="*"),
        ):
            with pytest.raises(grpc.aio.AioRpcError) as err:
                await read(stub.Listen(request))
            assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        held = stub.Listen(pb.ListenRequest(service="dev", property="a"))
        await events_until_sync(held)
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await read(stub.Listen(pb.ListenRequest(service="dev", property="b")))
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "max_streams" in err.value.details()
        held.cancel()


async def test_get_more_all_or_nothing(stub, dev) -> None:
    gw: Gateway = stub.gateway
    gw.router.add("dev2", DictBackend({"q": "9"}))
    reply = await stub.Get(
        pb.GetRequest(
            service="dev",
            property="a",
            more=[pb.PropertyRef(property="b"), pb.PropertyRef(service="dev2", property="q")],
        )
    )
    assert reply.value == "1"
    assert [(m.service, m.property, m.value) for m in reply.more] == [("dev", "b", "2"), ("dev2", "q", "9")]
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await stub.Get(pb.GetRequest(service="dev", property="a", more=[pb.PropertyRef(property="zz")]))
    assert err.value.code() == grpc.StatusCode.NOT_FOUND
    assert "dev/zz" in err.value.details()


async def test_set_returns_the_answer_and_refuses_read_only(stub, dev) -> None:
    assert (await stub.Set(pb.SetRequest(service="dev", property="a", value="7"))).value == "7"
    assert dev.values["a"] == "7"
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await stub.Set(pb.SetRequest(service="dev", property="ro", value="x"))
    assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION


async def test_bad_requests_are_invalid_argument(stub) -> None:
    for request in (pb.GetRequest(service="", property="a"), pb.GetRequest(service="dev", property="a..b")):
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await stub.Get(request)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


async def test_slow_backend_is_deadline_exceeded(dev) -> None:
    slow = DictBackend({"a": "1"}, delay=3.0)
    async with (
        running_gateway(slow, name="slow", config=config()) as gw,
        grpc.aio.insecure_channel(gw.address) as channel,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await stub.Get(pb.GetRequest(service="slow", property="a"))
        assert err.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        assert "slow: get a" in err.value.details()


async def test_crashing_backend_is_internal_and_logged(dev, caplog) -> None:
    class Broken(DictBackend):
        async def get(self, path, params=None):  # type: ignore[override]
            raise ZeroDivisionError("oops")

    broken = {"broken": Broken({"a": "1"})}
    async with (
        running_gateway(broken, config=config()) as gw,
        grpc.aio.insecure_channel(gw.address) as channel,
    ):
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await pb_grpc.PropertyServiceStub(channel).Get(pb.GetRequest(service="broken", property="a"))
    assert err.value.code() == grpc.StatusCode.INTERNAL
    assert "ZeroDivisionError" in caplog.text


async def test_shutdown_ends_listen_streams_with_unavailable(dev) -> None:
    async with (
        running_gateway(dev, name="dev", config=config()) as gw,
        grpc.aio.insecure_channel(gw.address) as channel,
    ):
        call = pb_grpc.PropertyServiceStub(channel).Listen(pb.ListenRequest(service="dev", property="a"))
        await events_until_sync(call)
        await gw.stop()
        with pytest.raises(grpc.aio.AioRpcError) as ended:
            await read(call)
        assert ended.value.code() == grpc.StatusCode.UNAVAILABLE
        assert ended.value.details() == "gateway shutting down"
    assert dev.closed
