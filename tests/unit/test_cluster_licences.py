"""Licences across gateways: claimed in the shared store by compare-and-set, so two never grant the same."""

from __future__ import annotations

import asyncio
import json

import pytest
from support.memory_store import MemoryServer
from support.waiting import wait_until

from gateway.cluster import ClusterLicences
from services.apps.registry import Licences
from services.apps.registry.store import Kind
from services.kernel.errors import Code, PropertyError


def _licences(server: MemoryServer, gateway: str) -> Licences:
    licences = Licences(lambda name: True)
    licences.set_claims(ClusterLicences(server.store(gateway)))
    return licences


async def test_a_licence_granted_on_one_gateway_is_refused_on_another() -> None:
    server = MemoryServer()
    a, b = _licences(server, "gw-a"), _licences(server, "gw-b")
    granted = await a.grant("arm", "alice", 30.0)
    held = json.loads(server.value(Kind.LICENCE, "arm") or "[]")
    assert [(c["id"], c["holder"], c["gateway"]) for c in held] == [(granted.id, "alice", "gw-a")]
    with pytest.raises(PropertyError) as refused:
        await b.grant("arm", "bob", 30.0)
    assert refused.value.code is Code.FAILED_PRECONDITION
    assert f"licence {granted.id} on arm is held by alice" in refused.value.message
    assert "granted by gateway gw-a" in refused.value.message
    assert b.held() == []
    await a.release(granted.id)
    await wait_until(lambda: server.value(Kind.LICENCE, "arm") is None, what="the key deleted on release")
    again = await b.grant("arm", "bob", 30.0)
    assert again.holder == "bob"


async def test_two_gateways_racing_for_one_licence_grant_it_once() -> None:
    server = MemoryServer()
    gateways = [_licences(server, f"gw-{i}") for i in range(4)]
    outcomes = await asyncio.gather(
        *(g.grant("arm", f"holder-{i}", 30.0) for i, g in enumerate(gateways)), return_exceptions=True
    )
    won = [o for o in outcomes if not isinstance(o, BaseException)]
    lost = [o for o in outcomes if isinstance(o, PropertyError)]
    assert len(won) == 1 and len(lost) == 3
    assert all(e.code is Code.FAILED_PRECONDITION for e in lost)


async def test_subtrees_that_do_not_overlap_are_licensed_on_different_gateways() -> None:
    server = MemoryServer()
    a, b = _licences(server, "gw-a"), _licences(server, "gw-b")
    await a.grant("bot", "alice", 30.0, "gripper")
    await b.grant("bot", "bob", 30.0, "camera")
    with pytest.raises(PropertyError, match="held by alice"):
        await b.grant("bot", "carol", 30.0, "gripper.open")
    assert len(json.loads(server.value(Kind.LICENCE, "bot") or "[]")) == 2


async def test_an_expired_claim_does_not_hold_and_a_renewal_is_written() -> None:
    server = MemoryServer()
    a, b = _licences(server, "gw-a"), _licences(server, "gw-b")
    granted = await a.grant("arm", "alice", 0.2)
    renewed = await a.renew(granted.id, 0.4)
    expires = json.loads(server.value(Kind.LICENCE, "arm") or "[]")[0]["expires"]
    assert abs(expires - renewed.expires_at) < 0.01
    await asyncio.sleep(0.5)
    # gw-a died without releasing (its claim stays in the key): past its time it holds nothing.
    a.set_claims(None)
    granted_b = await b.grant("arm", "bob", 30.0)
    assert [c["holder"] for c in json.loads(server.value(Kind.LICENCE, "arm") or "[]")] == ["bob"]
    assert granted_b.holder == "bob"


async def test_no_licence_while_the_store_cannot_be_reached() -> None:
    server = MemoryServer()
    a = _licences(server, "gw-a")
    server.stop("connection refused")
    with pytest.raises(PropertyError) as refused:
        await a.grant("arm", "alice", 30.0)
    assert refused.value.code is Code.UNAVAILABLE
    assert "read-only" in refused.value.message
    assert a.held() == []


async def test_a_licence_that_expires_deletes_its_key() -> None:
    server = MemoryServer()
    a = _licences(server, "gw-a")
    await a.grant("arm", "alice", 0.2)
    assert server.value(Kind.LICENCE, "arm") is not None
    await wait_until(
        lambda: server.value(Kind.LICENCE, "arm") is None, within=3.0, what="expiry deletes the key"
    )
    assert a.held() == []


def _watching(server: MemoryServer, gateway: str) -> Licences:
    """A gateway's licences whose claims also mirror the store's licences keys, as a node wires them."""
    licences = Licences(lambda name: True)
    store = server.store(gateway)
    claims = ClusterLicences(store)
    store.watch(
        lambda change: claims.observe(change.name, change.value) if change.kind is Kind.LICENCE else None
    )
    licences.set_claims(claims)
    return licences


async def test_a_set_is_checked_against_the_licences_other_gateways_granted() -> None:
    server = MemoryServer()
    a, b = _watching(server, "gw-a"), _watching(server, "gw-b")
    granted = await a.grant("arm", "alice", 0.6, "gripper")

    def refused_on_b() -> bool:
        try:
            b.check_set("arm", "gripper.open", "bob")
        except PropertyError:
            return True
        return False

    await wait_until(refused_on_b, what="gw-b sees gw-a's licence")
    with pytest.raises(PropertyError) as refusal:
        b.check_set("arm", "gripper.open", "bob")
    assert refusal.value.code is Code.FAILED_PRECONDITION
    assert f"licence {granted.id} on arm/gripper is held by alice" in refusal.value.message
    b.check_set("arm", "gripper.open", "alice")  # its holder
    b.check_set("arm", "camera", "bob")  # outside the subtree
    assert b.holder_of("arm") is not None and b.held() == []  # gw-b holds none itself
    # A gateway is not checked against its own claims twice: gw-a's local table answers there.
    assert a.holder_of("arm", "gripper") is granted
    # Once its time has passed, the licence holds nowhere, even before anyone deletes its key.
    a.set_claims(None)
    await asyncio.sleep(0.7)
    b.check_set("arm", "gripper.open", "bob")
    assert b.holder_of("arm") is None


async def test_a_released_licence_stops_holding_on_the_other_gateways() -> None:
    server = MemoryServer()
    a, b = _watching(server, "gw-a"), _watching(server, "gw-b")
    granted = await a.grant("arm", "alice", 30.0)
    await wait_until(lambda: b.holder_of("arm") is not None, what="gw-b sees the licence")
    await a.release(granted.id)
    await wait_until(lambda: b.holder_of("arm") is None, what="gw-b sees it released")
    b.check_set("arm", "speed", "bob")
