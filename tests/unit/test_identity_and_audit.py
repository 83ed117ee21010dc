"""Callers named from tokens and certificates; the audit trail and its token bucket; the config keys."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import ec

from gateway.audit import Audit, AuditSection, TokenBucket
from gateway.config import ConfigError, loads_config
from gateway.engine.guard import Guard, registry_operation
from gateway.engine.identity import ANONYMOUS, Authenticator, AuthSection, bearer_token, certificate_subject
from gateway.engine.rules import Operation, Subject
from services.kernel.errors import InvalidArgument, NotFound, Unauthenticated

SECRET = "correct horse battery staple, long enough for HS256"


def hs256(claims: dict[str, object], secret: str = SECRET) -> str:
    return jwt.encode(claims, secret, algorithm="HS256")


def fresh(**claims: object) -> dict[str, object]:
    # Made when the tests are collected, which may be long before they run: a day outlives any run.
    return {"sub": "alice", "exp": int(time.time()) + 86_400, **claims}


@pytest.fixture
def secret_file(tmp_path: Path) -> Path:
    path = tmp_path / "jwt.secret"
    path.write_text(SECRET + "\n")
    return path


def test_a_good_hs256_token_names_its_subject_and_scopes(secret_file: Path) -> None:
    auth = Authenticator(AuthSection(jwt_secret_file=str(secret_file)))
    subject = auth.identify([("authorization", "Bearer " + hs256(fresh(scope="read:scout1")))], {})
    assert subject.name == "alice" and subject.authenticated and subject.via == "token"
    assert subject.scopes is not None and subject.scopes.allow(Operation.READ, "scout1", "x")
    assert not subject.scopes.allow(Operation.WRITE, "scout1", "x")


@pytest.mark.parametrize(
    ("token", "why"),
    [
        (hs256({"sub": "alice", "exp": int(time.time()) - 60}), "Signature has expired"),
        (hs256({"sub": "alice"}), 'Token is missing the "exp" claim'),
        (
            hs256(fresh(), secret="another secret, also long enough for HS256"),
            "Signature verification failed",
        ),
        (hs256(fresh(sub="")), "sub"),
        (hs256(fresh(scope="fly:scout1")), "unknown operation 'fly'"),
        ("not.a.token", "bearer token refused"),
        (jwt.encode(fresh(), None, algorithm="none"), "algorithm 'none' is not accepted"),
    ],
    # Named by the reason, not the token: a token holds the time it was made, and the test ids must
    # be the same in every process that collects them (pytest-xdist's workers).
    ids=["expired", "no-exp", "wrong-secret", "empty-sub", "unknown-operation", "not-a-token", "alg-none"],
)
def test_bad_tokens_are_unauthenticated_naming_why(secret_file: Path, token: str, why: str) -> None:
    auth = Authenticator(AuthSection(jwt_secret_file=str(secret_file)))
    with pytest.raises(Unauthenticated, match="bearer token refused") as caught:
        auth.identify([("authorization", f"Bearer {token}")], {})
    assert why in caught.value.message


def test_issuer_and_audience_are_checked_when_configured(secret_file: Path) -> None:
    auth = Authenticator(AuthSection(jwt_secret_file=str(secret_file), issuer="lab", audience="gw1"))
    assert auth.subject_of_token(hs256(fresh(iss="lab", aud="gw1"))).name == "alice"
    with pytest.raises(Unauthenticated, match="Invalid issuer"):
        auth.subject_of_token(hs256(fresh(iss="elsewhere", aud="gw1")))
    with pytest.raises(Unauthenticated, match="Audience doesn't match"):
        auth.subject_of_token(hs256(fresh(iss="lab", aud="gw2")))


def test_a_jwks_file_checks_es256_tokens_by_kid(tmp_path: Path) -> None:
    key = ec.generate_private_key(ec.SECP256R1())
    public = json.loads(jwt.algorithms.ECAlgorithm.to_jwk(key.public_key()))
    (tmp_path / "keys.json").write_text(json.dumps({"keys": [{**public, "kid": "k1", "alg": "ES256"}]}))
    auth = Authenticator(AuthSection(jwks_file=str(tmp_path / "keys.json")))
    token = jwt.encode(fresh(sub="bob"), key, algorithm="ES256", headers={"kid": "k1"})
    assert auth.subject_of_token(token).name == "bob"
    stranger = ec.generate_private_key(ec.SECP256R1())
    forged = jwt.encode(fresh(sub="bob"), stranger, algorithm="ES256", headers={"kid": "k1"})
    with pytest.raises(Unauthenticated, match="Signature verification failed"):
        auth.subject_of_token(forged)
    with pytest.raises(Unauthenticated, match="no key 'k9'"):
        auth.subject_of_token(jwt.encode(fresh(), key, algorithm="ES256", headers={"kid": "k9"}))
    # Without a secret file an HS256 token is not accepted at all.
    with pytest.raises(Unauthenticated, match="algorithm 'HS256' is not accepted"):
        auth.subject_of_token(hs256(fresh()))


def test_key_files_that_cannot_be_used_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgument, match=r"auth\.jwt_secret_file: cannot read"):
        Authenticator(AuthSection(jwt_secret_file=str(tmp_path / "missing")))
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(InvalidArgument, match=r"auth\.jwks_file: .* is not a usable JSON Web Key Set"):
        Authenticator(AuthSection(jwks_file=str(tmp_path / "bad.json")))


def test_certificates_name_their_subject_by_cn_then_san() -> None:
    cn = certificate_subject({"x509_common_name": [b"robot-arm"], "x509_subject_alternative_name": [b"x"]})
    assert cn == Subject("robot-arm", authenticated=True, via="certificate")
    san = certificate_subject({"x509_subject_alternative_name": [b"ops.example"]})
    assert san is not None and san.name == "ops.example"
    assert certificate_subject({"transport_security_type": [b"ssl"]}) is None
    # A token wins over the certificate; without [auth] tokens are not looked at.
    auth = Authenticator(AuthSection())
    ctx = {"x509_common_name": [b"robot-arm"]}
    assert auth.identify([("authorization", "Bearer garbage")], ctx).name == "robot-arm"
    assert auth.identify(None, {}) is ANONYMOUS


def test_authorization_metadata_must_be_a_bearer_token() -> None:
    assert bearer_token([("x", "y"), ("authorization", "Bearer abc")]) == "abc"
    assert bearer_token(None) is None
    with pytest.raises(Unauthenticated, match="Bearer TOKEN"):
        bearer_token([("authorization", "Basic dXNlcg==")])


def test_registry_sets_are_register_unregister_or_admin() -> None:
    assert registry_operation("services.scout4", "tcp://127.0.0.1:7001") is Operation.REGISTER
    assert registry_operation("services.scout4", "") is Operation.UNREGISTER
    assert registry_operation("services.scout4.lease", "30") is Operation.ADMIN
    assert registry_operation("period", "1") is Operation.ADMIN


def test_the_token_bucket_refills_at_its_rate() -> None:
    now = [0.0]
    bucket = TokenBucket(rate=2.0, burst=3, clock=lambda: now[0])
    assert [bucket.take() for _ in range(4)] == [True, True, True, False]
    now[0] = 0.5
    assert bucket.take() and not bucket.take()
    now[0] = 100.0
    assert sum(bucket.take() for _ in range(10)) == 3


def test_audit_lines_are_json_rate_limited_and_report_what_they_dropped(
    caplog: pytest.LogCaptureFixture,
) -> None:
    now = [0.0]
    audit = Audit(AuditSection(rate=1.0, burst=2), clock=lambda: now[0])
    alice = Subject("alice", True, via="token")
    with caplog.at_level(logging.INFO, logger="gateway.audit"):
        for _ in range(1000):
            audit.record(alice, "scout1", "speed", Operation.WRITE)
        audit.record(alice, "scout1", "speed", Operation.WRITE, NotFound("scout1: no speed"))
        assert len(caplog.records) == 2 and audit.suppressed == 999
        now[0] = 1.0
        audit.record(ANONYMOUS, "registry", "services.x", Operation.REGISTER, Unauthenticated("who?"))
    lines = [json.loads(r.getMessage()) for r in caplog.records]
    assert lines[0] == {
        "subject": "alice",
        "via": "token",
        "service": "scout1",
        "property": "speed",
        "operation": "write",
        "outcome": "ok",
    }
    assert lines[2] == {"suppressed": 999}
    assert lines[3]["outcome"] == "UNAUTHENTICATED" and lines[3]["message"] == "who?"
    assert lines[3]["subject"] == "anonymous" and lines[3]["via"] == "none"
    assert all(r.name == "gateway.audit" for r in caplog.records)


def test_config_reads_auth_rules_and_audit(secret_file: Path) -> None:
    config = loads_config(
        f"""
        [auth]
        jwt_secret_file = "{secret_file.name}"
        issuer = "lab"
        [[rules]]
        subject = "*"
        operations = ["read"]
        effect = "permit"
        [[rules]]
        subject = ["alice", "bob"]
        service = "scout1"
        path = "behaviors.**"
        operations = "invoke"
        effect = "permit"
        [audit]
        rate = 5
        burst = 10
        """,
        folder=secret_file.parent,
    )
    assert config.auth.jwt_secret_file == str(secret_file) and config.auth.issuer == "lab"
    assert [r.text for r in config.rules] == [
        "permit * read */**",
        "permit [alice, bob] invoke scout1/behaviors.**",
    ]
    assert config.audit == AuditSection(rate=5.0, burst=10)
    guard = Guard.from_config(config)
    assert guard.checks
    assert not Guard.from_config(loads_config("")).checks


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ('[auth]\njwt_secret_file = "nowhere.secret"', "auth.jwt_secret_file: cannot read"),
        ('[auth]\nkey = "x"', "auth.key: unknown key"),
        ('[[rules]]\nsubject = "a"\noperations = ["read"]', "rules[0]: missing key 'effect'"),
        ('[[rules]]\nsubject = "a"\noperations = ["fly"]\neffect = "permit"', "unknown operation 'fly'"),
        (
            '[[rules]]\nsubject = "a"\npath = "a.**.b"\noperations = ["read"]\neffect = "deny"',
            "rules[0].path",
        ),
        ('[[rules]]\nsubject = "a"\noperations = ["read"]\neffect = "permit"\nwho = 1', "rules[0].who"),
        ("[audit]\nrate = -1", "audit.rate: must not be negative"),
    ],
)
def test_config_mistakes_name_the_key(tmp_path: Path, text: str, problem: str) -> None:
    with pytest.raises(ConfigError) as caught:
        loads_config(text, "gw.toml", tmp_path)
    assert problem in str(caught.value)
