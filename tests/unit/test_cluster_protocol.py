"""Cluster protocol versions: in the gateways' keys and in the calls between gateways.

A gateway joins a cluster on a store held in memory (tests/support/memory_store.py); a call that
another gateway would make reaches a real gateway served in this process (gateway.testing) with
the ``ps-protocols`` metadata a gateway of each version sends.
"""

from __future__ import annotations

import json

import grpc
import pytest
from support.fake_backend import DictBackend
from support.memory_store import MemoryServer

from gateway.cluster import ClusterNode
from gateway.cluster.records import GatewayRecord, read_gateway
from gateway.engine.router import Router
from gateway.peer_protocol import (
    PROTOCOLS_KEY,
    SPOKEN,
    UNVERSIONED,
    ProtocolMismatch,
    format_protocols,
    parse_protocols,
)
from gateway.testing import running_gateway
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.apps.registry import Registry
from services.apps.registry.store import Kind

#: The gateways key a gateway of the previous release writes: no versions in it.
PREVIOUS_RELEASE_KEY = json.dumps({"address": "127.0.0.1:50061", "http": "", "line": "", "owned": 0})


async def _join(server: MemoryServer, gateway_id: str) -> tuple[ClusterNode, Registry]:
    store = server.store(gateway_id)
    await store.start()
    router = Router()
    node = ClusterNode(store, router, lease=1.0)
    registry = Registry(directory=node.directory, period=0, store=store, restore=False)
    await registry.start()
    try:
        await node.start(registry, address="127.0.0.1:50062")
    except BaseException:
        await node.stop()
        await registry.stop()
        raise
    return node, registry


async def test_a_gateway_says_its_protocols_and_joins_a_cluster_of_the_previous_release() -> None:
    server = MemoryServer()
    older = server.store("gw-old")
    await older.start()
    await older.put(Kind.GATEWAY, "gw-old", PREVIOUS_RELEASE_KEY, leased=True)

    node, registry = await _join(server, "gw-new")
    try:
        keys = await older.read(Kind.GATEWAY)
        assert json.loads(keys["gw-new"])["protocols"] == sorted(SPOKEN)
        assert node.view.gateways["gw-old"].protocols == UNVERSIONED
        assert node.joined
    finally:
        await node.stop()
        await registry.stop()


async def test_a_gateway_refuses_to_join_a_cluster_whose_gateways_speak_no_protocol_it_speaks() -> None:
    server = MemoryServer()
    newer = server.store("gw-future")
    await newer.start()
    future = GatewayRecord("127.0.0.1:50061", protocols=frozenset({max(SPOKEN) + 5}))
    await newer.put(Kind.GATEWAY, "gw-future", future.to_json(), leased=True)

    with pytest.raises(ProtocolMismatch) as refused:
        await _join(server, "gw-here")
    message = refused.value.message
    assert f"speaks cluster protocol {', '.join(map(str, sorted(SPOKEN)))}" in message
    assert f"gw-future speaks {max(SPOKEN) + 5}" in message
    assert "cannot run together" in message
    assert set(await newer.read(Kind.GATEWAY)) == {"gw-future"}, "the refused gateway wrote its key"


def test_a_gateways_key_keeps_its_protocols_and_one_without_them_is_the_first_protocol() -> None:
    record = GatewayRecord("10.0.0.5:50051", "10.0.0.5:8080", owned=3, protocols=frozenset({2, 3}))
    assert read_gateway(record.to_json()) == record
    previous = read_gateway(PREVIOUS_RELEASE_KEY)
    assert previous is not None and previous.protocols == UNVERSIONED
    for bad in ("[]", '"2"', "[0]", "[true]", "[1.5]"):
        text = PREVIOUS_RELEASE_KEY[:-1] + f', "protocols": {bad}}}'
        assert read_gateway(text) is None, bad


def test_the_protocols_metadata_reads_back_and_refuses_what_is_not_a_list_of_versions() -> None:
    assert parse_protocols(format_protocols(SPOKEN)) == SPOKEN
    assert parse_protocols(b"1") == frozenset({1})
    for bad in ("", "two", "1,,2", "0", "-1", ",".join(["1"] * 40)):
        assert parse_protocols(bad) is None, bad


@pytest.mark.parametrize(
    ("sent", "answered"),
    [
        (None, grpc.StatusCode.OK),  # a client, or a gateway of the first protocol
        ("1", grpc.StatusCode.OK),
        (format_protocols(SPOKEN), grpc.StatusCode.OK),
        (f"{max(SPOKEN)},{max(SPOKEN) + 1}", grpc.StatusCode.OK),  # a newer gateway that still speaks ours
        (str(max(SPOKEN) + 1), grpc.StatusCode.FAILED_PRECONDITION),
        ("garbage", grpc.StatusCode.FAILED_PRECONDITION),
    ],
)
async def test_a_call_from_a_gateway_is_answered_when_they_share_a_protocol(
    sent: str | None, answered: grpc.StatusCode
) -> None:
    async with (
        running_gateway(DictBackend({"temperature": "21.5"}), name="thermo") as gateway,
        grpc.aio.insecure_channel(gateway.address) as channel,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)
        metadata = ((PROTOCOLS_KEY, sent), ("ps-via", "gw-other")) if sent is not None else ()
        request = pb.GetRequest(service="thermo", property="temperature")
        try:
            reply = await stub.Get(request, metadata=metadata, timeout=5)
        except grpc.aio.AioRpcError as exc:
            assert exc.code() == answered, exc.details()
            assert "cluster protocol" in (exc.details() or "")
        else:
            assert answered == grpc.StatusCode.OK
            assert reply.value == "21.5"
        listen = stub.Listen(
            pb.ListenRequest(service="thermo", property="temperature"),
            metadata=metadata,
            timeout=5,
        )
        try:
            async for _ in listen:
                break
        except grpc.aio.AioRpcError as exc:
            assert exc.code() == answered, exc.details()
        else:
            assert answered == grpc.StatusCode.OK
        listen.cancel()
