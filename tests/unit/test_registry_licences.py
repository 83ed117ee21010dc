"""Licences and service states in the registry itself: the API the scheduler and the gateway call."""

from __future__ import annotations

import asyncio

import pytest
from support.waiting import wait_until

from services.apps.registry import Lease, Licence, Registry
from services.apps.registry.lease import now
from services.kernel.backend import BackendInfo, Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, PropertyError


@pytest.fixture
def registry() -> Registry:
    registry = Registry(max_licences=3, max_licence_duration=60)
    for name in ("scout", "spare", "robot-a"):
        registry.add(name, BackendInfo(type="mobile_robot", url=f"tcp://{name}:1"))
    return registry


async def test_grant_holder_of_and_the_refusals_name_holder_and_expiry(registry: Registry) -> None:
    licences = registry.licensing
    licence = await licences.grant("scout", "robot-a", 30, "behaviors")
    assert isinstance(licence, Licence)
    assert (licence.service, licence.subtree, licence.holder, licence.status) == (
        "scout", "behaviors", "robot-a", "held"
    )  # fmt: skip
    assert 29 < licence.left() <= 30 and licence.expires > now() and licence.expires_at > licence.granted
    assert licences.holder_of("scout", "behaviors.moveto") is licence
    assert licences.holder_of("scout", "behaviors") is licence
    assert licences.holder_of("scout", "behaviorsx") is None
    assert licences.holder_of("scout", "velocity") is None
    assert licences.holder_of("scout") is licence  # any licence on it
    licences.check_set("scout", "behaviors.moveto", "robot-a")  # its holder
    licences.check_set("scout", "velocity", "someone")  # outside the subtree
    with pytest.raises(PropertyError) as refused:
        licences.check_set("scout", "behaviors.moveto", "someone")
    assert refused.value.code is Code.FAILED_PRECONDITION
    assert f"licence {licence.id} on scout/behaviors is held by robot-a until 20" in refused.value.message
    with pytest.raises(PropertyError, match="held by robot-a") as overlap:
        await licences.grant("scout", "someone", 5)
    assert overlap.value.code is Code.FAILED_PRECONDITION
    with pytest.raises(PropertyError, match=f"robot-a already holds licence {licence.id}") as twice:
        await licences.grant("scout", "robot-a", 5, "behaviors.moveto")
    assert twice.value.code is Code.FAILED_PRECONDITION
    for duration in (0, -1, 61, float("nan")):
        with pytest.raises(PropertyError) as bad:
            await licences.grant("spare", "robot-a", duration)
        assert bad.value.code is Code.INVALID_ARGUMENT
    with pytest.raises(PropertyError) as unknown:
        await licences.grant("nowhere", "robot-a", 5)
    assert unknown.value.code is Code.NOT_FOUND


async def test_renew_release_and_the_bound_on_licences(registry: Registry) -> None:
    licences = registry.licensing
    a = await licences.grant("scout", "alice", 1)
    renewed = await licences.renew(a.id, 50, holder="alice")
    assert renewed is a and a.left() > 40
    with pytest.raises(PropertyError) as stolen:
        await licences.release(a.id, holder="bob")
    assert stolen.value.code is Code.PERMISSION_DENIED
    await licences.grant("spare", "alice", 5)
    await licences.grant("robot-a", "bob", 5)
    registry.add("extra", BackendInfo(type="sensor", url="tcp://extra:1"))
    with pytest.raises(PropertyError) as full:
        await licences.grant("extra", "carol", 5)
    assert full.value.code is Code.RESOURCE_EXHAUSTED
    await licences.release(a.id, holder="alice")
    assert a.status == "released"
    with pytest.raises(PropertyError, match="no longer held: it was released") as ended:
        await licences.renew(a.id, 5)
    assert ended.value.code is Code.FAILED_PRECONDITION
    with pytest.raises(PropertyError) as never:
        licences.get("L99-000000")
    assert never.value.code is Code.NOT_FOUND


async def test_a_licence_expires_by_itself_and_listeners_hear_every_change(registry: Registry) -> None:
    heard: list[tuple[str, str]] = []
    registry.licensing.watch(lambda licence, event: heard.append((licence.id, event)))
    licence = await registry.licensing.grant("scout", "alice", 0.05)
    await wait_until(lambda: licence.status == "expired", what="expiry")
    assert heard == [(licence.id, "granted"), (licence.id, "expired")]
    assert registry.licensing.held() == []


async def test_holders_that_vanish_lose_their_licences(registry: Registry) -> None:
    licences = registry.licensing
    on_session = await licences.grant("scout", "session-ab", 30, session="ab")
    by_robot = await licences.grant("spare", "robot-a", 30)
    assert licences.release_session("other") == []
    assert licences.release_session("ab") == [on_session] and on_session.status == "lost"
    registry.set_state("robot-a", "down")  # the holder is a registered service, and it died
    assert by_robot.status == "lost"
    on_scout = await licences.grant("scout", "alice", 30)
    registry.remove("scout")  # the licensed service left
    assert on_scout.status == "lost"


async def test_availability_follows_state_dormancy_and_licences(registry: Registry) -> None:
    svc = LocalService(registry)
    changes: list[Change] = []
    await svc.listen("services.spare.availability", changes.append)
    assert await svc.get("services.spare.availability") == "ready"
    registry.set_dormant("spare", True)
    licence = await registry.licensing.grant("spare", "alice", 30)
    assert await svc.get("services.spare.availability") == "dormant"
    registry.set_dormant("spare", False)
    assert await svc.get("services.spare.licence") == licence.id
    await registry.licensing.release(licence.id)
    registry.set_state("spare", "down")
    assert [c.value for c in changes] == ["dormant", "active", "ready", "death"]
    assert await svc.get("services.spare.state") == "down"


async def test_the_registry_properties_show_licences_and_their_end(registry: Registry) -> None:
    svc = LocalService(registry)
    licence = await svc.set("acquire", "", {"service": "scout", "duration": "30"})
    assert await svc.get("licences") == f"({licence})"
    changes: list[Change] = []
    await svc.listen(f"licences.{licence}", changes.append)
    await svc.set("renew", "", {"licence": licence, "duration": "40"})
    await svc.set("release", "", {"licence": licence})
    assert await svc.get("licences") == "()"
    assert "<status>released</status>" in await svc.get(f"licences.{licence}")  # how it ended
    assert ["<status>held</status>" in c.value for c in changes] == [True, False]
    registry.add("registry-b", BackendInfo(type="registry", url="grpc://b:1"))
    with pytest.raises(PropertyError, match="a registry is never licensed"):
        await svc.set("acquire", "", {"service": "registry-b"})


def test_a_lease_is_one_deadline_for_liveness_and_licences() -> None:
    lease = Lease()
    assert not lease.held and lease.left() == 0 and not lease.lapsed()
    lease.renew(10)
    assert lease.held and 9 < lease.left() <= 10 and not lease.lapsed()
    assert lease.until is not None and lease.lapsed(lease.until + 0.001)
    lease.end()
    assert not lease.held


async def test_the_expiry_timer_stops_with_the_registry(registry: Registry) -> None:
    await registry.licensing.grant("scout", "alice", 30)
    await registry.stop()
    await asyncio.sleep(0)
    assert registry.licensing._timer is None


async def test_one_holder_holds_a_few_licences_and_an_admin_revokes_any() -> None:
    registry = Registry(max_licences=10, max_licences_per_holder=2)
    for name in ("scout", "spare", "arm", "cam"):
        registry.add(name, BackendInfo(type="mobile_robot", url=f"tcp://{name}:1"))
    licences = registry.licensing
    events: list[tuple[str, str]] = []
    licences.watch(lambda licence, event: events.append((licence.id, event)))
    first = await licences.grant("scout", "squatter", 30)
    await licences.grant("spare", "squatter", 30)
    with pytest.raises(PropertyError, match=r"squatter holds 2 licences already") as capped:
        await licences.grant("arm", "squatter", 30)
    assert capped.value.code is Code.RESOURCE_EXHAUSTED
    await licences.grant("arm", "someone", 30)  # others are not held back
    # The scheduler bounds its own grants (allocations per consumer): they are not capped here.
    scheduled = await licences.grant("cam", "squatter", 30, limit_holder=False)
    assert licences.count_held_by("squatter") == 3
    await licences.release(scheduled.id)

    revoked = licences.revoke(first.id)
    assert revoked.status == "revoked" and (first.id, "revoked") in events
    assert licences.holder_of("scout") is None
    with pytest.raises(PropertyError, match="no longer held: it was revoked") as ended:
        await licences.renew(first.id, 10, holder="squatter")
    assert ended.value.code is Code.FAILED_PRECONDITION
    with pytest.raises(PropertyError, match="no longer held: it was revoked"):
        licences.revoke(first.id)
    again = await licences.grant("scout", "squatter", 30)  # room again under its bound
    assert again.holder == "squatter"
