"""Session: many tagged Get, Set and Listen requests over one bidirectional stream."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import grpc
import pytest
from support.fake_backend import DictBackend
from support.session_stream import replies_until

from gateway.app import Gateway
from gateway.config import Config, GatewaySection
from gateway.testing import running_gateway
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.apps.simulators import SimRobot

WAIT = 5.0


@pytest.fixture
async def gateway() -> AsyncIterator[Gateway]:
    backends = {
        "dev": DictBackend({"a": "1", "b": "2", "ro": "x"}, readonly=("ro",)),
        "slow": DictBackend({"a": "s"}, delay=0.2),
        "bot": SimRobot(speed=50.0),
    }
    cfg = Config(gateway=GatewaySection(call_timeout=2.0))
    async with running_gateway(backends, config=cfg) as gw:
        yield gw


@pytest.fixture
async def session(gateway: Gateway) -> AsyncIterator[grpc.aio.StreamStreamCall]:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        call = pb_grpc.PropertyServiceStub(channel).Session()
        yield call
        call.cancel()


def get(rid: int, service: str, prop: str) -> pb.Request:
    return pb.Request(id=rid, get=pb.GetRequest(service=service, property=prop))


def by_id(replies: list[pb.Reply]) -> dict[int, list[pb.Reply]]:
    out: dict[int, list[pb.Reply]] = {}
    for r in replies:
        out.setdefault(r.id, []).append(r)
    return out


async def test_mixed_requests_answered_by_id_and_errors_do_not_end_the_stream(session) -> None:
    await session.write(
        pb.SessionRequest(
            requests=[
                get(1, "dev", "a"),
                get(2, "slow", "a"),
                pb.Request(id=3, set=pb.SetRequest(service="dev", property="b", value="20")),
                get(4, "dev", "missing"),
                pb.Request(id=5, set=pb.SetRequest(service="dev", property="ro", value="y")),
                get(6, "bot", "speed"),
                get(7, "nowhere", "a"),
            ]
        )
    )
    replies = by_id(await replies_until(session, lambda rs: len(rs) >= 7))
    assert replies[1][0].get.value == "1"
    assert replies[2][0].get.value == "s"
    assert replies[3][0].set.value == "20"
    assert replies[4][0].status.code == grpc.StatusCode.NOT_FOUND.value[0]
    assert replies[5][0].status.code == grpc.StatusCode.FAILED_PRECONDITION.value[0]
    assert replies[6][0].get.value == "50"
    assert replies[7][0].status.code == grpc.StatusCode.NOT_FOUND.value[0]
    # The stream lives on after failures.
    await session.write(pb.SessionRequest(requests=[get(8, "dev", "b")]))
    (reply,) = await replies_until(session, lambda rs: len(rs) >= 1)
    assert (reply.id, reply.get.value) == (8, "20")


async def test_listen_in_a_session_then_cancel(session, gateway) -> None:
    dev: DictBackend = gateway.router.backend("dev")  # type: ignore[assignment]
    await session.write(
        pb.SessionRequest(requests=[pb.Request(id=10, listen=pb.ListenRequest(service="dev", property="a"))])
    )
    first = await replies_until(session, lambda rs: any(r.listen.sync for r in rs))
    assert all(r.id == 10 for r in first)
    assert [e.value for r in first for e in r.listen.events] == ["1"]
    dev.put("a", "2")
    (change,) = await replies_until(session, lambda rs: len(rs) >= 1)
    assert (change.id, [e.value for e in change.listen.events]) == (10, ["2"])

    await session.write(pb.SessionRequest(requests=[pb.Request(id=11, cancel=pb.Cancel(id=10))]))
    replies = by_id(await replies_until(session, lambda rs: len(rs) >= 2))
    assert replies[10][-1].status.code == grpc.StatusCode.CANCELLED.value[0]
    assert replies[11][0].status.code == 0
    assert gateway.hub.stream_count == 0
    # Cancelling what is not running is NOT_FOUND on the cancel's own reply.
    await session.write(pb.SessionRequest(requests=[pb.Request(id=12, cancel=pb.Cancel(id=10))]))
    (reply,) = await replies_until(session, lambda rs: len(rs) >= 1)
    assert (reply.id, reply.status.code) == (12, grpc.StatusCode.NOT_FOUND.value[0])


async def test_duplicate_active_id_is_invalid_argument(session) -> None:
    listen = pb.Request(id=1, listen=pb.ListenRequest(service="dev", property="a"))
    await session.write(pb.SessionRequest(requests=[listen]))
    await replies_until(session, lambda rs: any(r.listen.sync for r in rs))
    await session.write(pb.SessionRequest(requests=[get(1, "dev", "a")]))
    (reply,) = await replies_until(session, lambda rs: len(rs) >= 1)
    assert (reply.id, reply.status.code) == (1, grpc.StatusCode.INVALID_ARGUMENT.value[0])


async def test_listen_errors_arrive_on_their_reply(session) -> None:
    await session.write(
        pb.SessionRequest(
            requests=[pb.Request(id=3, listen=pb.ListenRequest(service="dev", property="nope"))]
        )
    )
    (reply,) = await replies_until(session, lambda rs: len(rs) >= 1)
    assert (reply.id, reply.status.code) == (3, grpc.StatusCode.NOT_FOUND.value[0])


async def test_half_close_finishes_outstanding_requests_then_ends(session) -> None:
    await session.write(
        pb.SessionRequest(
            requests=[
                get(1, "slow", "a"),
                pb.Request(id=2, listen=pb.ListenRequest(service="dev", property="a")),
            ]
        )
    )
    await session.done_writing()
    replies: list[pb.Reply] = []
    async with asyncio.timeout(WAIT):
        while (msg := await session.read()) is not grpc.aio.EOF:
            replies.extend(msg.replies)
    assert by_id(replies)[1][0].get.value == "s"
    assert await session.code() == grpc.StatusCode.OK


async def test_many_gets_in_one_message(session) -> None:
    n = 2000
    await session.write(pb.SessionRequest(requests=[get(i, "bot", "speed") for i in range(n)]))
    replies = await replies_until(session, lambda rs: len(rs) >= n)
    assert sorted(r.id for r in replies) == list(range(n))
    assert {r.get.value for r in replies} == {"50"}


async def test_gateway_shutdown_ends_sessions_with_unavailable(gateway) -> None:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        call = pb_grpc.PropertyServiceStub(channel).Session()
        await call.write(
            pb.SessionRequest(
                requests=[pb.Request(id=1, listen=pb.ListenRequest(service="dev", property="a"))]
            )
        )
        await replies_until(call, lambda rs: any(r.listen.sync for r in rs))
        await gateway.stop()
        with pytest.raises(grpc.aio.AioRpcError) as ended:
            async with asyncio.timeout(WAIT):
                while await call.read() is not grpc.aio.EOF:
                    pass
        assert ended.value.code() == grpc.StatusCode.UNAVAILABLE
        assert ended.value.details() == "gateway shutting down"
