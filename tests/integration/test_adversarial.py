"""Bad input never crashes anything and loses nothing; every queue, buffer and wait is bounded.

Raw generated stubs against an in-process gateway (so the tests can look at the hub's and the
sessions' internals) over services the tests control. After every test the gateway must still
answer a plain Get, hold no Listen stream and no topic, and have logged no ERROR.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Awaitable
from typing import Any

import grpc
import pytest
from google.protobuf.duration_pb2 import Duration
from support.fake_backend import DictBackend
from support.session_stream import replies_until
from support.waiting import wait_until

from gateway.app import Gateway
from gateway.config import Config, GatewaySection, Limits
from gateway.fronts.grpc_v1.session import Session
from gateway.testing import running_gateway
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.apps.simulators import SimRobot
from services.kernel.backend import NO_PARAMS

WAIT = 10.0
U64_MAX = 2**64 - 1
OK = grpc.StatusCode.OK.value[0]
CANCELLED = grpc.StatusCode.CANCELLED.value[0]
INVALID_ARGUMENT = grpc.StatusCode.INVALID_ARGUMENT.value[0]
NOT_FOUND = grpc.StatusCode.NOT_FOUND.value[0]
RESOURCE_EXHAUSTED = grpc.StatusCode.RESOURCE_EXHAUSTED.value[0]
#: grpc's default largest message a client receives.
GRPC_MAX_MESSAGE = 4 * 1024 * 1024

LIMITS = Limits(max_streams=20, session_max_in_flight=16, session_max_queued_replies=64, max_selectors=64)


class CountingBackend(DictBackend):
    """A DictBackend whose reads wait one loop turn and count how many run at once."""

    def __init__(self) -> None:
        super().__init__({"a": "1"})
        self.running = 0
        self.most = 0

    async def get(self, path: str, params: Any = NO_PARAMS) -> str:
        self.running += 1
        self.most = max(self.most, self.running)
        try:
            await asyncio.sleep(0)
            return await super().get(path, params)
        finally:
            self.running -= 1


@pytest.fixture
def dev() -> DictBackend:
    return DictBackend({"a": "1", "b": "2", "big1": "", "big2": "", "big3": ""})


@pytest.fixture
def counting() -> CountingBackend:
    return CountingBackend()


@pytest.fixture
async def gw(
    dev: DictBackend, counting: CountingBackend, caplog: pytest.LogCaptureFixture
) -> AsyncIterator[Gateway]:
    backends = {
        "dev": dev,
        "count": counting,
        "slow": DictBackend({"a": "s"}, delay=0.5),
        "bot": SimRobot(speed=5.0),
    }
    cfg = Config(gateway=GatewaySection(call_timeout=2.0), limits=LIMITS)
    caplog.set_level(logging.WARNING)
    async with running_gateway(backends, config=cfg) as gateway:
        yield gateway
        # The gateway is healthy after whatever the test did.
        async with grpc.aio.insecure_channel(gateway.address) as channel:
            reply = await pb_grpc.PropertyServiceStub(channel).Get(
                pb.GetRequest(service="dev", property="b"), timeout=WAIT
            )
            assert reply.value == "2"
        await wait_until(lambda: gateway.hub.stream_count == 0 and gateway.hub.topic_count == 0)
        await wait_until(lambda: not gateway.servicer.sessions)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]


@pytest.fixture
async def stub(gw: Gateway) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with grpc.aio.insecure_channel(gw.address) as channel:
        yield pb_grpc.PropertyServiceStub(channel)


async def rpc_error(awaitable: Awaitable[Any]) -> grpc.aio.AioRpcError:
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await asyncio.wait_for(awaitable, WAIT)
    return err.value


def get(rid: int, service: str = "dev", prop: str = "a") -> pb.Request:
    return pb.Request(id=rid, get=pb.GetRequest(service=service, property=prop))


def listen(rid: int, service: str = "dev", prop: str = "a") -> pb.Request:
    return pb.Request(id=rid, listen=pb.ListenRequest(service=service, property=prop))


async def read_to_end(call: Any) -> list[pb.Reply]:
    out: list[pb.Reply] = []
    async with asyncio.timeout(WAIT):
        while (msg := await call.read()) is not grpc.aio.EOF:
            out.extend(msg.replies)
    return out


def seconds(s: float) -> Duration:
    d = Duration()
    d.FromNanoseconds(int(s * 1e9))
    return d


def the_session(gw: Gateway) -> Session:
    (session,) = gw.servicer.sessions
    return session


# -- Session ---------------------------------------------------------------------------------


async def test_session_bad_requests_get_their_own_status_and_the_stream_lives(stub) -> None:
    call = stub.Session()
    await call.write(
        pb.SessionRequest(
            requests=[
                pb.Request(id=7),  # no call
                listen(0),
                listen(U64_MAX),
                listen(0),  # id in use by a running listen
                pb.Request(id=3, cancel=pb.Cancel(id=12345)),  # unknown id
                pb.Request(id=4, cancel=pb.Cancel(id=U64_MAX - 1)),
                pb.Request(id=5, get=pb.GetRequest()),  # empty
                pb.Request(id=6, set=pb.SetRequest(service="dev", property="a..b", value="x")),
            ]
        )
    )
    replies = await replies_until(
        call, lambda rs: sum(r.listen.sync for r in rs) == 2 and sum(r.HasField("status") for r in rs) >= 6
    )
    status = {r.id: r.status.code for r in replies if r.HasField("status")}
    assert status == {
        7: INVALID_ARGUMENT,
        0: INVALID_ARGUMENT,
        3: NOT_FOUND,
        4: NOT_FOUND,
        5: INVALID_ARGUMENT,
        6: INVALID_ARGUMENT,
    }
    assert {r.id for r in replies if r.listen.sync} == {0, U64_MAX}
    # Both listens are alive and cancellable by their extreme ids.
    await call.write(
        pb.SessionRequest(
            requests=[
                pb.Request(id=8, cancel=pb.Cancel(id=0)),
                pb.Request(id=9, cancel=pb.Cancel(id=U64_MAX)),
            ]
        )
    )
    replies = await replies_until(call, lambda rs: len(rs) >= 4)
    assert sorted((r.id, r.status.code) for r in replies) == [
        (0, CANCELLED),
        (8, OK),
        (9, OK),
        (U64_MAX, CANCELLED),
    ]
    await call.done_writing()
    assert await read_to_end(call) == []
    assert await call.code() == grpc.StatusCode.OK


async def test_100k_requests_in_one_message_run_at_most_max_in_flight(stub, counting) -> None:
    n = 100_000
    call = stub.Session()
    await call.write(pb.SessionRequest(requests=[get(i, "count") for i in range(n)]))
    await call.done_writing()
    replies = await read_to_end(call)
    assert len(replies) == n
    assert {r.get.value for r in replies} == {"1"}
    assert counting.most <= LIMITS.session_max_in_flight


async def test_a_session_that_never_reads_keeps_a_bounded_queue(stub, gw) -> None:
    call = stub.Session()
    most_queued = most_tasks = 0
    for batch in range(100):
        try:
            await asyncio.wait_for(
                call.write(
                    pb.SessionRequest(requests=[get(batch * 200 + i, "bot", "speed") for i in range(200)])
                ),
                0.5,
            )
        except TimeoutError:
            break  # flow control: the gateway stopped reading
        for session in gw.servicer.sessions:
            most_queued = max(most_queued, len(session._replies))
            most_tasks = max(most_tasks, len(session._tasks))
    await asyncio.sleep(0.2)
    session = the_session(gw)
    most_queued = max(most_queued, len(session._replies))
    assert most_queued <= LIMITS.session_max_queued_replies
    assert most_tasks <= LIMITS.session_max_in_flight
    # Others are served meanwhile.
    assert (await stub.Get(pb.GetRequest(service="dev", property="a"), timeout=WAIT)).value == "1"
    call.cancel()


async def test_half_close_with_listens_open_ends_them_and_the_call(stub, gw) -> None:
    call = stub.Session()
    await call.write(pb.SessionRequest(requests=[listen(1), listen(2, "dev", "b"), get(3, "slow")]))
    await replies_until(call, lambda rs: sum(r.listen.sync for r in rs) == 2)
    await call.done_writing()
    replies = await read_to_end(call)
    assert [(r.id, r.get.value) for r in replies if r.HasField("get")] == [(3, "s")]
    assert await call.code() == grpc.StatusCode.OK


async def test_a_client_that_disappears_mid_batch_leaves_nothing(stub, gw, dev) -> None:
    for _ in range(5):
        call = stub.Session()
        requests = [get(i, "slow") for i in range(10)] + [listen(100 + i, "dev", "a") for i in range(10)]
        await call.write(pb.SessionRequest(requests=requests))
        await call.read()
        call.cancel()
    await wait_until(lambda: not gw.servicer.sessions and gw.hub.stream_count == 0)
    await wait_until(lambda: dev.listeners("a") == 0)


async def test_listens_beyond_max_streams_are_resource_exhausted_on_their_reply(stub, gw) -> None:
    n = LIMITS.max_streams + 5
    call = stub.Session()
    await call.write(pb.SessionRequest(requests=[listen(i) for i in range(n)]))
    replies = await replies_until(
        call, lambda rs: sum(r.listen.sync for r in rs) + sum(r.HasField("status") for r in rs) >= n
    )
    assert sum(r.listen.sync for r in replies) == LIMITS.max_streams
    refused = [r for r in replies if r.HasField("status")]
    assert len(refused) == 5
    assert {r.status.code for r in refused} == {RESOURCE_EXHAUSTED}
    assert "max_streams" in refused[0].status.message
    assert gw.hub.stream_count == LIMITS.max_streams
    call.cancel()


async def test_a_10mb_set_is_resource_exhausted_and_the_session_lives(stub) -> None:
    err = await rpc_error(stub.Set(pb.SetRequest(service="dev", property="a", value="x" * 10_000_000)))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "larger than max" in (err.details() or "")


async def test_session_replies_with_big_values_fit_in_messages(stub, dev) -> None:
    big = "v" * 1_500_000
    for name in ("big1", "big2", "big3"):
        dev.put(name, big)
    call = stub.Session()
    await call.write(pb.SessionRequest(requests=[get(i, "dev", f"big{i}") for i in (1, 2, 3)]))
    replies = await replies_until(call, lambda rs: len(rs) >= 3)
    assert sorted(r.id for r in replies) == [1, 2, 3]
    assert {len(r.get.value) for r in replies} == {len(big)}
    call.cancel()


# -- Listen ----------------------------------------------------------------------------------


async def test_listen_selector_limits_and_bad_patterns(stub) -> None:
    more = [pb.PropertyRef(property="a") for _ in range(10_000)]
    err = await rpc_error(stub.Listen(pb.ListenRequest(service="dev", property="a", more=more)).read())
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "at most 64 selectors" in (err.details() or "")
    for bad in ("**", "a.**", "a..b", ".a", "a.", "", "a" * 300, "a*", "a.b c", "\x00", "ü"):
        err = await rpc_error(stub.Listen(pb.ListenRequest(service="dev", property=bad)).read())
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, bad
        assert len(err.details() or "") < 300
    for bad_service in ("", "**", "a.b", "x" * 300):
        err = await rpc_error(stub.Listen(pb.ListenRequest(service=bad_service, property="a")).read())
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, bad_service


async def test_listen_star_star_sends_every_one_segment_property_then_sync(stub) -> None:
    call = stub.Listen(pb.ListenRequest(service="*", property="*"))
    events: list[pb.Event] = []
    async with asyncio.timeout(WAIT):
        while not (msg := await call.read()).sync:
            events.extend(msg.events)
    keys = {(e.service, e.property) for e in events}
    assert {("dev", "a"), ("count", "a"), ("slow", "a"), ("bot", "speed")} <= keys
    assert all("." not in e.property for e in events)
    call.cancel()


@pytest.mark.parametrize("option", ["min_interval", "sample_interval", "heartbeat_interval"])
async def test_listen_intervals_negative_tiny_zero_huge(stub, option) -> None:
    for bad in (seconds(-1), seconds(1e-6), Duration(seconds=1, nanos=-5)):
        opts = pb.ListenOptions(**{option: bad})
        err = await rpc_error(stub.Listen(pb.ListenRequest(service="dev", property="a", options=opts)).read())
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert option in (err.details() or "")
    ten_years = Duration(seconds=10 * 365 * 86400)
    beyond = Duration(seconds=2**62)
    for good in (Duration(), ten_years, beyond):
        opts = pb.ListenOptions(**{option: good})
        call = stub.Listen(pb.ListenRequest(service="dev", property="a", options=opts))
        async with asyncio.timeout(WAIT):
            while not (await call.read()).sync:
                pass
        call.cancel()


async def test_a_listen_that_never_reads_stays_conflated(stub, gw, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="a"))
    async with asyncio.timeout(WAIT):
        while not (await call.read()).sync:
            pass
    (stream,) = gw.hub._streams
    most = 0
    n = 100_000
    for i in range(n):
        dev.put("a", f"{i:>100}")
        if i % 1000 == 0:
            most = max(most, len(stream._pending))
            await asyncio.sleep(0)
    assert most <= 1
    last = ""
    conflated = 0
    async with asyncio.timeout(WAIT):
        while last != f"{n - 1:>100}":
            msg = await call.read()
            for event in msg.events:
                last = event.value
                conflated += event.conflated
    assert conflated > 0
    call.cancel()


async def test_big_values_in_a_listen_fit_in_messages(stub, dev) -> None:
    big = "v" * 1_500_000
    for name in ("big1", "big2", "big3"):
        dev.put(name, big)
    call = stub.Listen(
        pb.ListenRequest(
            service="dev",
            property="big1",
            more=[pb.PropertyRef(property="big2"), pb.PropertyRef(property="big3")],
        )
    )
    events: list[pb.Event] = []
    async with asyncio.timeout(WAIT):
        while not (msg := await call.read()).sync:
            events.extend(msg.events)
    assert [len(e.value) for e in events] == [len(big)] * 3
    call.cancel()


async def test_a_value_too_big_for_any_message_ends_the_listen_clearly(stub, dev) -> None:
    call = stub.Listen(pb.ListenRequest(service="dev", property="big1"))
    async with asyncio.timeout(WAIT):
        while not (await call.read()).sync:
            pass
    dev.put("big1", "v" * (GRPC_MAX_MESSAGE + 1))
    with pytest.raises(grpc.aio.AioRpcError) as err:
        async with asyncio.timeout(WAIT):
            while True:
                await call.read()
    assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "dev/big1: a value of" in (err.value.details() or "")


async def test_1000_listen_open_cancel_cycles_leak_nothing(stub, gw, dev) -> None:
    for i in range(1000):
        call = stub.Listen(pb.ListenRequest(service="dev", property="a" if i % 2 else "b"))
        if i % 3 == 0:
            await asyncio.wait_for(call.read(), WAIT)
        call.cancel()
    await wait_until(lambda: gw.hub.stream_count == 0 and gw.hub.topic_count == 0)
    await wait_until(lambda: dev.listeners("a") == 0 and dev.listeners("b") == 0)


# -- Get -------------------------------------------------------------------------------------


async def test_get_with_10000_more_is_resource_exhausted(stub) -> None:
    more = [pb.PropertyRef(property="a") for _ in range(10_000)]
    err = await rpc_error(stub.Get(pb.GetRequest(service="dev", property="a", more=more)))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "at most 1000 paths" in (err.details() or "")


async def test_get_with_10000_parameters_is_answered(stub) -> None:
    params = {f"k{i}": "v" * 10 for i in range(10_000)}
    assert (await stub.Get(pb.GetRequest(service="dev", property="a", parameters=params))).value == "1"


async def test_unicode_control_characters_and_nuls(stub) -> None:
    for name in ("sc\x00out", "ü" * 70, "a\nb", "x" * 100_000, "\u202e", "😀"):
        err = await rpc_error(stub.Get(pb.GetRequest(service=name, property="a")))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert len(err.details() or "") < 300
        err = await rpc_error(stub.Get(pb.GetRequest(service="dev", property=name)))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert len(err.details() or "") < 300
    value = "a\x00b\u2603\x01\U0001f600\x00"
    assert (await stub.Set(pb.SetRequest(service="dev", property="a", value=value))).value == value
    assert (await stub.Get(pb.GetRequest(service="dev", property="a"))).value == value


async def test_get_whose_values_outgrow_a_message_is_resource_exhausted(stub, dev) -> None:
    big = "v" * 1_500_000
    for name in ("big1", "big2", "big3"):
        dev.put(name, big)
    more = [pb.PropertyRef(property="big2"), pb.PropertyRef(property="big3")]
    err = await rpc_error(stub.Get(pb.GetRequest(service="dev", property="big1", more=more)))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "bytes" in (err.details() or "")
    # In a Session, the same Get fails on its own reply and the stream lives on.
    call = stub.Session()
    await call.write(
        pb.SessionRequest(
            requests=[pb.Request(id=1, get=pb.GetRequest(service="dev", property="big1", more=more))]
        )
    )
    (reply,) = await replies_until(call, lambda rs: len(rs) >= 1)
    assert reply.status.code == RESOURCE_EXHAUSTED
    await call.write(pb.SessionRequest(requests=[get(2)]))
    (reply,) = await replies_until(call, lambda rs: len(rs) >= 1)
    assert reply.get.value == "1"
    # One value too big for any message: the same, for a single Get.
    dev.put("big1", "v" * GRPC_MAX_MESSAGE)
    err = await rpc_error(stub.Get(pb.GetRequest(service="dev", property="big1")))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "dev: get big1: the answer is" in (err.details() or "")
    await call.write(pb.SessionRequest(requests=[get(3, "dev", "big1"), get(4)]))
    replies = await replies_until(call, lambda rs: len(rs) >= 2)
    assert sorted((r.id, r.status.code) for r in replies) == [(3, RESOURCE_EXHAUSTED), (4, OK)]
    call.cancel()


# -- Requests that do not parse --------------------------------------------------------------

BAD_UTF8 = b"\x0a\x03\xff\xfe\xfd"  # field 1 (a string) holding bytes that are not UTF-8


async def test_requests_with_bad_utf8_are_invalid_argument(gw) -> None:
    from gateway.fronts.grpc_v1.servicer import add_to_server

    server = grpc.aio.server()
    add_to_server(gw.servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        async with grpc.aio.insecure_channel(f"127.0.0.1:{port}") as channel:
            method = "/propertyservice.v1.PropertyService/"
            for name in ("Get", "Set"):
                err = await rpc_error(channel.unary_unary(method + name)(BAD_UTF8))
                assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, name
                assert "UTF-8" in (err.details() or "")
            call = channel.unary_stream(method + "Listen")(BAD_UTF8)
            err = await rpc_error(call.read())
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
            request = b"\x08\x01\x12" + bytes([len(BAD_UTF8)]) + BAD_UTF8
            session = channel.stream_stream(method + "Session")()
            await session.write(pb.SessionRequest(requests=[get(5)]).SerializeToString())
            await session.write(b"\x0a" + bytes([len(request)]) + request)
            replies = []
            with pytest.raises(grpc.aio.AioRpcError) as bad:
                async with asyncio.timeout(WAIT):
                    while (msg := await session.read()) is not grpc.aio.EOF:
                        replies.extend(pb.SessionResponse.FromString(msg).replies)
            assert bad.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            # What was read before the bad message is answered first.
            assert [(r.id, r.get.value) for r in replies] == [(5, "1")]
            # The same channel still works.
            reply = await channel.unary_unary(method + "Get")(
                pb.GetRequest(service="dev", property="a").SerializeToString()
            )
            assert pb.GetResponse.FromString(reply).value == "1"
    finally:
        await server.stop(None)


# -- A real gateway process ------------------------------------------------------------------


async def test_a_real_gateway_survives_the_bad_inputs_and_logs_no_error(gateway_process) -> None:
    proc = gateway_process('[[services]]\nname = "bot"\ntype = "sim-robot"\n')
    async with grpc.aio.insecure_channel(proc.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        err = await rpc_error(
            stub.Set(pb.SetRequest(service="bot", property="speed", value="x" * 10_000_000))
        )
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        err = await rpc_error(stub.Set(pb.SetRequest(service="bot", property="speed", value="y" * 1_000_000)))
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert len(err.details() or "") < 300
        for name in ("sc\x00out", "a\nb", "x" * 100_000, "😀", "**"):
            err = await rpc_error(stub.Get(pb.GetRequest(service="bot", property=name)))
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        more = [pb.PropertyRef(property="speed")] * 10_000
        err = await rpc_error(stub.Get(pb.GetRequest(service="bot", property="speed", more=more)))
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        err = await rpc_error(stub.Listen(pb.ListenRequest(service="bot", property="a", more=more)).read())
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        opts = pb.ListenOptions(min_interval=seconds(-1))
        err = await rpc_error(stub.Listen(pb.ListenRequest(service="*", property="*", options=opts)).read())
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        call = stub.Session()
        await call.write(
            pb.SessionRequest(
                requests=[pb.Request(id=1), get(U64_MAX, "bot", "speed"), listen(0, "bot", "speed")]
            )
        )
        replies = await replies_until(call, lambda rs: len(rs) >= 3 and any(r.listen.sync for r in rs))
        assert {r.id for r in replies} == {1, U64_MAX, 0}
        call.cancel()
        for _ in range(100):
            listen_call = stub.Listen(pb.ListenRequest(service="bot", property="location"))
            listen_call.cancel()
        assert (await stub.Get(pb.GetRequest(service="bot", property="speed"), timeout=WAIT)).value
    assert proc.stop() == 0
    assert "Traceback" not in proc.output
    assert " ERROR " not in proc.output and "ERROR:" not in proc.output, proc.output
