"""The cluster as a gateway last heard it, and the plan of who takes an orphan over."""

from __future__ import annotations

import asyncio
from xml.etree import ElementTree

from support.waiting import wait_until

from gateway.cluster import ClusterView, GatewayRecord, Registration, takeover_ranks
from gateway.cluster.failover import Takeover
from gateway.cluster.picture import draw_owners
from gateway.cluster.records import Ownership, read_gateway, read_registration
from services.apps.registry.store import Change, Kind


def test_records_round_trip_and_bad_values_are_refused() -> None:
    registration = Registration("tcp://127.0.0.1:7001", {"type": "sensor"})
    assert read_registration(registration.to_json()) == registration
    assert registration.declared_type == "sensor" and not registration.dialled_in
    assert Registration("tcp-in://127.0.0.1:5000").dialled_in
    record = GatewayRecord("127.0.0.1:50051", http="127.0.0.1:8080", line="127.0.0.1:7100", owned=3)
    assert read_gateway(record.to_json()) == record
    for bad in ("", "{", "[]", '{"url": 3}', '{"options": {}}', '{"url": "x", "options": []}'):
        assert read_registration(bad) is None, bad
    for bad in ("", "{}", '{"address": ""}', '{"address": "a:1", "owned": "many"}'):
        assert read_gateway(bad) is None, bad


def test_a_change_names_the_services_it_concerns() -> None:
    view = ClusterView()
    reg = Registration("tcp://127.0.0.1:7001").to_json()
    assert view.apply(Change(Kind.SERVICE, "bot", reg)) == ["bot"]
    assert view.apply(Change(Kind.SERVICE, "bot", reg)) == []  # nothing new
    assert view.apply(Change(Kind.OWNER, "bot", "gw-a")) == ["bot"]
    assert view.apply(Change(Kind.STATE, "bot", "up")) == ["bot"]
    assert view.apply(Change(Kind.STATE, "bot", "sideways")) == ["bot"]  # not a state: as if absent
    assert "bot" not in view.states
    record = GatewayRecord("127.0.0.1:50051").to_json()
    # A gateway's address concerns every service it owns; a new count of what it owns, none.
    assert view.apply(Change(Kind.GATEWAY, "gw-a", record)) == ["bot"]
    counted = GatewayRecord("127.0.0.1:50051", owned=1).to_json()
    assert view.apply(Change(Kind.GATEWAY, "gw-a", counted)) == []
    assert view.apply(Change(Kind.GATEWAY, "gw-a", None)) == ["bot"]
    assert view.apply(Change(Kind.SERVICE, "bot", "not json")) == ["bot"]
    assert "bot" not in view.registrations


def test_a_full_read_replaces_what_was_heard() -> None:
    view = ClusterView()
    reg = Registration("tcp://127.0.0.1:7001").to_json()
    view.apply(Change(Kind.SERVICE, "old", reg))
    view.apply(Change(Kind.OWNER, "old", "gw-a"))
    names = view.replace({Kind.SERVICE: {"new": reg}, Kind.OWNER: {}})
    assert names == ["new", "old"]
    assert list(view.registrations) == ["new"] and view.owners == {}


def test_loads_and_orphans() -> None:
    view = ClusterView()
    for gateway in ("gw-a", "gw-b", "gw-c"):
        view.apply(Change(Kind.GATEWAY, gateway, GatewayRecord(f"{gateway}:1").to_json()))
    for name, owner in (("s1", "gw-a"), ("s2", "gw-a"), ("s3", "gw-b"), ("s4", None), ("s5", None)):
        view.apply(Change(Kind.SERVICE, name, Registration(f"tcp://127.0.0.1:70{name[1]}0").to_json()))
        if owner:
            view.apply(Change(Kind.OWNER, name, owner))
    view.apply(Change(Kind.SERVICE, "dialled", Registration("tcp-in://127.0.0.1:4000").to_json()))
    assert view.loads() == {"gw-a": 2, "gw-b": 1, "gw-c": 0}
    # A device that dialled in is never an orphan to take over: nobody can dial it.
    assert view.orphans() == ["s4", "s5"]
    assert view.owned_by("gw-a") == ["s1", "s2"]


def test_orphans_are_dealt_to_the_least_loaded_first() -> None:
    loads = {"gw-a": 2, "gw-b": 0, "gw-c": 0}
    plans = {me: takeover_ranks(["s3", "s1", "s2", "s4"], loads, me) for me in loads}
    # Each orphan has exactly one gateway at rank 0, and every gateway agrees on it.
    names = ("s1", "s2", "s3", "s4")
    firsts = {name: [me for me, plan in plans.items() if plan[name] == 0] for name in names}
    assert firsts == {"s1": ["gw-b"], "s2": ["gw-c"], "s3": ["gw-b"], "s4": ["gw-c"]}
    # The others stand behind in the order of their load: a second tries when the first cannot.
    assert sorted(plan["s1"] for plan in plans.values()) == [0, 1, 2]
    assert plans["gw-a"]["s1"] == 2
    assert takeover_ranks(["s1"], {"gw-a": 0}, "gw-z") == {}  # not a live gateway (yet)


async def test_the_orphans_of_one_rank_are_attempted_together_a_step_apart() -> None:
    loop = asyncio.get_running_loop()
    orphans = [f"s{n}" for n in range(6)]
    attempts: list[tuple[float, list[str]]] = []

    async def attempt(names: list[str]) -> None:
        attempts.append((loop.time(), sorted(names)))
        for name in names:
            orphans.remove(name)  # owned now: the next plan leaves it out

    takeover = Takeover(
        "gw-b", step=0.2, plan=lambda: (list(orphans), {"gw-b": 0, "gw-c": 0}), attempt=attempt
    )
    try:
        takeover.orphaned()
        takeover.orphaned()  # a burst of orphans: one plan
        await wait_until(lambda: len(attempts) == 2, what="one attempt per rank")
        takeover.orphaned()  # nothing left: no attempt
        await asyncio.sleep(0.3)
    finally:
        await takeover.aclose()
    (first_at, first), (second_at, second) = attempts
    # gw-b is first for every other orphan (ties go to the smaller id), second for the rest.
    assert first == ["s0", "s2", "s4"] and second == ["s1", "s3", "s5"]
    assert second_at - first_at >= 0.19
    assert len(attempts) == 2


def test_the_picture_shows_each_gateway_with_what_it_owns() -> None:
    gateways = {
        "gw1": GatewayRecord("127.0.0.1:50061", line="127.0.0.1:7101"),
        "gw2": GatewayRecord("127.0.0.1:50062"),
    }
    registrations = {
        "thermo1": Registration("tcp://127.0.0.1:7001"),
        "rover2": Registration("tcp-in://127.0.0.1:40000"),
        "lost": Registration("tcp://127.0.0.1:7003"),
    }
    owners = {"thermo1": "gw1", "rover2": "gw2"}
    svg = draw_owners(Ownership("etcd://127.0.0.1:2379", gateways, owners, registrations))
    root = ElementTree.fromstring(svg)  # well-formed SVG
    texts = [t.text or "" for t in root.iter("{http://www.w3.org/2000/svg}text")]
    assert "etcd://127.0.0.1:2379" in texts
    assert "gRPC 127.0.0.1:50061 · line 127.0.0.1:7101" in texts
    assert {"gw1", "gw2", "thermo1", "rover2", "tcp-in://127.0.0.1:40000"} <= set(texts)
    assert "owned by no live gateway: lost" in texts
