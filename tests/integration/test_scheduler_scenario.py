"""The multi-robot SOA seed's scenario through a real gateway process.

Robot A asks for help with a survey. B and C are free and are dispatched with licences; D and E
are dormant, and are woken when B and C are busy. A second request for the same service by A is
refused (rule e). The survey licences expire at ``Tout``, and a licence used after that is refused.
A releases and records QoS in the seed's normalised format: B 0.86, C 0, D 0.94, E 0.82.
Every robot proves who it is with a bearer token; A is a registered robot too (rule f), never
chosen while it is a consumer (rule a).
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import jwt
import pytest
from support.gateway_process import GatewayProcess
from support.waiting import eventually

from clients import AsyncClient, ClientCredentials
from clients.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    ResourceExhausted,
    Unavailable,
)
from services.kernel.values import parse_list

SECRET = "a shared secret of the lab, long enough for HS256"

ROBOTS = """
[auth]
jwt_secret_file = "jwt.secret"

[registry]
tout = TOUT
tr = 5
max_queued = 2

[[services]]
name = "A"
type = "sim-robot"
features = ["survey"]
options = { start = [0.0, 0.0] }

[[services]]
name = "B"
type = "sim-robot"
features = ["survey"]
options = { start = [1.0, 0.0] }

[[services]]
name = "C"
type = "sim-robot"
features = ["survey"]
options = { start = [2.0, 0.0] }

[[services]]
name = "D"
type = "sim-robot"
features = ["survey"]
dormant = true
options = { start = [3.0, 0.0] }

[[services]]
name = "E"
type = "sim-robot"
features = ["survey"]
dormant = true
options = { start = [4.0, 0.0] }
"""

LICENCE = re.compile(r"L\d+-[0-9a-f]{6}")


def token(subject: str) -> str:
    return jwt.encode({"sub": subject, "exp": int(time.time()) + 600}, SECRET, algorithm="HS256")


def robot(gw: GatewayProcess, who: str) -> AsyncClient:
    return AsyncClient(gw.address, credentials=ClientCredentials(token=token(who)))


@pytest.fixture
def site(gateway_process, tmp_path: Path) -> GatewayProcess:  # type: ignore[no-untyped-def]
    """The robots with a Tout of 6 s: licences expire within the test."""
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(ROBOTS.replace("TOUT", "6"))  # type: ignore[no-any-return]


@pytest.fixture
def long_site(gateway_process, tmp_path: Path) -> GatewayProcess:  # type: ignore[no-untyped-def]
    """The robots with a Tout of 60 s: nothing expires while the test waits for the queue."""
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(ROBOTS.replace("TOUT", "60"))  # type: ignore[no-any-return]


def granted(answer: str) -> tuple[str, dict[str, str]]:
    allocation, status, pairs = parse_list(answer)
    assert status == "granted", answer
    licences = {provider: licence for provider, licence in pairs}
    assert all(LICENCE.fullmatch(lic) for lic in licences.values()), answer
    return allocation, licences


async def test_the_seed_scenario(site: GatewayProcess) -> None:
    async with robot(site, "A") as a, robot(site, "F") as f:
        for name in ("D", "E"):
            assert await a.get("registry", f"services.{name}.availability") == "dormant"
        assert await a.get("registry", "services.B.features") == "(survey)"
        # A's location is followed by the registry: the request's cost is the drive from there.
        await eventually(lambda: a.get("registry", "services.B.location"), lambda v: v.startswith("(1 0"))

        # B and C: free, nearest; dispatched with licences. D and E stay dormant.
        first, survey = granted(await a.set("registry", "request", "(survey)", count="2"))
        assert sorted(survey) == ["B", "C"]
        for name in ("B", "C"):
            assert await a.get("registry", f"services.{name}.availability") == "active"
        assert await a.get("registry", "services.D.availability") == "dormant"
        # The licence is A's: F is refused on B, A may act.
        with pytest.raises(FailedPrecondition, match="held by A until"):
            await f.set("B", "velocity", "(0.1 0)")
        await a.set("B", "velocity", "(0.1 0)")

        # Rule (e): the same service again, by the same consumer, while it holds it.
        with pytest.raises(FailedPrecondition, match=r"rule \(e\): A already holds \(survey\)"):
            await a.set("registry", "request", "(survey)", count="2")

        # B and C are busy, A is a consumer (rule a): D and E are woken (rule c: A holds both).
        second, helpers = granted(await a.set("registry", "request", "(mobile_robot)", count="2"))
        assert sorted(helpers) == ["D", "E"]
        for name in ("D", "E"):
            assert await a.get("registry", f"services.{name}.availability") == "active"
        assert "dormant, starting it" in site.output

        # Nobody is free for F now; it may not wait: a clear status, nothing allocated.
        with pytest.raises(Unavailable, match="busy"):
            await f.set("registry", "request", "(survey)", wait="0")

        # The survey licences expire at Tout (6 s here): B and C are free, the licence is dead.
        await eventually(
            lambda: a.get("registry", "services.B.availability"), lambda v: v == "ready", within=15
        )
        with pytest.raises(FailedPrecondition, match="no longer held: it was expired"):
            await a.set("registry", "renew", "", licence=survey["B"])
        assert f"({first} " not in await a.get("registry", "allocations")

        # A releases both and records QoS in the normalised format.
        assert (
            await a.set("registry", "release", "", allocation=first, qos="((B 0.86) (C 0))")
            == "((B 0.86) (C 0))"
        )
        assert await a.set("registry", "release", "", allocation=second, qos="((D 0.94) (E 0.82))")
        assert await a.get("registry", "qos") == "((B 0.86) (C 0) (D 0.94) (E 0.82))"
        assert await a.get("registry", "qos.D") == "0.94"
        assert await a.get("registry", "qos.D.count") == "1"
        for name in ("D", "E"):
            assert await a.get("registry", f"services.{name}.availability") in ("ready", "dormant")
        assert await a.get("registry", "allocations") == "()"

        # QoS now counts: with the cost weighing nothing, D (0.94) is chosen before B (0.86).
        chosen = granted(await f.set("registry", "request", "(survey)", weight="0"))[1]
        assert list(chosen) == ["D"]


async def test_bad_requests_get_clear_statuses_and_nothing_stays_allocated(long_site: GatewayProcess) -> None:
    site = long_site
    async with (
        robot(site, "A") as a,
        robot(site, "F") as f,
        robot(site, "G") as g,
        robot(site, "H") as h,
        robot(site, "I") as i,
        robot(site, "J") as j,
    ):
        with pytest.raises(NotFound, match=r"no provider offers \(laser\)"):
            await a.set("registry", "request", "(laser)")
        with pytest.raises(NotFound, match="no composition covers"):
            await a.set("registry", "request", "(laser survey)")
        with pytest.raises(NotFound, match="6 providers offering all of"):
            await a.set("registry", "request", "(survey)", count="6")
        assert await a.get("registry", "unserved") == "((A (laser)) (A (laser survey)) (A (survey)))"
        for bad, match in (
            ({"count": "0"}, "count must be 1 to"),
            ({"duration": "61"}, "Tout = 60 s"),
            ({"wait": "6"}, "Tr = 5 s"),
            ({"wait": "-1"}, "Tr = 5 s"),
            ({"duration": "-1"}, "more than 0"),
            ({"cost": "a..b"}, "bad parameter cost"),
            ({"weight": "2"}, "weight must be 0 to 1"),
            ({"location": "(1 x)"}, "bad parameter location"),
            ({"location": "(1)"}, "at least x and y"),
            ({"exclude": "(B"}, "bad parameter exclude"),
        ):
            with pytest.raises(InvalidArgument, match=match):
                await a.set("registry", "request", "(survey)", **bad)
        with pytest.raises(InvalidArgument, match="capability name"):
            await a.set("registry", "request", "(bad!name)")
        # A robot that proved who it is asks only for itself: naming another would spend that
        # robot's turn (rule e) and keep it from providing (rule a).
        with pytest.raises(PermissionDenied, match="G may request only as itself: consumer=B"):
            await g.set("registry", "request", "(survey)", consumer="B")
        assert await g.get("registry", "allocations") == "()"
        # An anonymous unary caller cannot hold licences.
        async with AsyncClient(site.address) as anonymous:
            with pytest.raises(FailedPrecondition, match="anonymous caller"):
                await anonymous.set("registry", "request", "(survey)")

        # A flood: the first four take every provider but A, two wait, the next is refused.
        held = [
            granted(await who.set("registry", "request", caps))[0]
            for who, caps in ((a, "(survey)"), (f, "(survey)"), (g, "(survey)"), (a, "(mobile_robot)"))
        ]
        assert len(held) == 4
        waiting = [await who.set("registry", "request", "(survey)", wait="5") for who in (h, i)]
        assert all(parse_list(w)[1] == "queued" for w in waiting)
        requests = await a.get("registry", "requests")
        assert [row[0] for row in parse_list(requests)] == [parse_list(w)[0] for w in waiting]
        with pytest.raises(ResourceExhausted, match="queue is full"):
            await j.set("registry", "request", "(survey)", wait="5")

        # A release serves the first waiting request: it shows in the allocations, the queue shrinks.
        with pytest.raises(PermissionDenied, match="only it may release it"):
            await f.set("registry", "release", "", allocation=held[0])
        await a.set("registry", "release", "", allocation=held[0])
        served = parse_list(waiting[0])[0]
        await eventually(lambda: a.get("registry", "allocations"), lambda v: f"({served} H " in v)
        assert [row[0] for row in parse_list(await a.get("registry", "requests"))] == [
            parse_list(waiting[1])[0]
        ]
        # The other waits its 5 s (Tr) and is dropped.
        await eventually(lambda: a.get("registry", "requests"), lambda v: v == "()", within=10)
        with pytest.raises(NotFound, match="no allocation"):
            await a.set("registry", "release", "", allocation="r999")
        with pytest.raises(InvalidArgument, match="one of the parameters licence or allocation"):
            await a.set("registry", "release", "")


async def test_an_anonymous_consumer_holds_its_allocation_on_its_session_and_loses_it_with_it(
    site: GatewayProcess,
) -> None:
    async with AsyncClient(site.address) as anonymous, robot(site, "F") as f:
        async with anonymous.session() as session:
            allocation, chosen = granted(
                await session.set("registry", "request", "(survey)", consumer="scout", location="(1 0)")
            )
            assert list(chosen) == ["B"]
            await session.set("B", "velocity", "(0.1 0)")  # the holder: its own Session
            with pytest.raises(FailedPrecondition, match=r"held by session-[0-9a-f]{16} until"):
                await f.set("B", "velocity", "(0 0)")
            assert f"({allocation} scout (survey)" in await f.get("registry", "allocations")
        # The Session ended: its licences were lost, the allocation with them, and B is free.
        await eventually(lambda: f.get("registry", "allocations"), lambda v: v == "()")
        assert await f.get("registry", "services.B.availability") == "ready"
        assert list(granted(await f.set("registry", "request", "(survey)", location="(1 0)"))[1]) == ["B"]
