"""Every crafted token is UNAUTHENTICATED: any header, any key, any claims, signed or not, through the
real verifier (:class:`gateway.engine.identity.Authenticator`)."""

from __future__ import annotations

import base64
import json
import time
from pathlib import Path
from typing import Any

import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jwt.algorithms import get_default_algorithms

from gateway.engine.identity import Authenticator, AuthSection
from gateway.engine.rules import Subject
from services.kernel.errors import Unauthenticated

SECRET = "correct horse battery staple, long enough for HS256, HS384 and even HS512 keys"

#: One key of each kind a JWKS may hold, by kid; made once (an RSA key takes a while).
PRIVATE_KEYS: dict[str, Any] = {
    "rsa": rsa.generate_private_key(public_exponent=65537, key_size=2048),
    "p256": ec.generate_private_key(ec.SECP256R1()),
    "p384": ec.generate_private_key(ec.SECP384R1()),
    "ed": ed25519.Ed25519PrivateKey.generate(),
}
ALGORITHMS = sorted(get_default_algorithms())


def b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def signed(header: dict[str, Any], claims: Any, key: Any) -> str:
    """A token with exactly ``header`` and ``claims``, signed with ``key`` by the header's own
    ``alg`` where the library can (a signature that verifies, so that the claims are looked at),
    else carrying a signature of junk."""
    signing_input = f"{b64(json.dumps(header).encode())}.{b64(json.dumps(claims).encode())}"
    name = header.get("alg")
    algorithm = get_default_algorithms().get(name) if isinstance(name, str) else None
    try:
        assert algorithm is not None
        signature = algorithm.sign(signing_input.encode(), algorithm.prepare_key(key))
    except Exception:  # a key the algorithm cannot sign with: the token carries junk instead
        signature = b"\x00" * 64
    return f"{signing_input}.{b64(signature)}"


@pytest.fixture(scope="module")
def authenticator(tmp_path_factory: pytest.TempPathFactory) -> Authenticator:
    folder: Path = tmp_path_factory.mktemp("keys")
    keys = []
    for kid, private in PRIVATE_KEYS.items():
        algorithm = {"rsa": "RS256", "p256": "ES256", "p384": "ES384", "ed": "EdDSA"}[kid]
        jwk = json.loads(get_default_algorithms()[algorithm].to_jwk(private.public_key()))
        keys.append({**jwk, "kid": kid})
    (folder / "jwks.json").write_text(json.dumps({"keys": keys}))
    (folder / "secret").write_text(SECRET)
    return Authenticator(
        AuthSection(
            jwt_secret_file=str(folder / "secret"),
            jwks_file=str(folder / "jwks.json"),
            issuer="lab",
            audience="gw1",
        )
    )


def check(authenticator: Authenticator, token: str) -> Subject | None:
    """The subject, or None for a refusal; anything but Unauthenticated fails the test."""
    try:
        subject = authenticator.subject_of_token(token)
    except Unauthenticated as refused:
        assert refused.message.startswith("bearer token refused")
        return None
    assert isinstance(subject.name, str) and subject.name
    return subject


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=8,
)
headers = st.fixed_dictionaries(
    {},
    optional={
        "alg": st.sampled_from(ALGORITHMS) | json_values,
        "kid": st.sampled_from(sorted(PRIVATE_KEYS)) | json_values,
        "typ": json_values,
        "crit": json_values,
        "b64": json_values,
        "jku": json_values,
        "x5c": json_values,
    },
)


def good_or_junk(good: Any) -> st.SearchStrategy[Any]:
    """Mostly the good value, so that the checks after it are reached; else any JSON value."""
    return st.one_of(st.just(good), st.just(good), json_values)


claims = (
    st.fixed_dictionaries(
        {
            "sub": good_or_junk("alice"),
            "exp": good_or_junk(int(time.time()) + 86_400 * 365),
            "iss": good_or_junk("lab"),
            "aud": good_or_junk("gw1"),
        },
        optional={
            "nbf": json_values,
            "iat": json_values,
            "scope": st.sampled_from(["read:scout1", "write:scout1.speed read:*", ["read:*"]]) | json_values,
        },
    )
    | json_values
)
#: Who signs: the key the header's kid names (or the secret), so that most signatures verify; else another.
MATCHING = "the key the header names"


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    header=headers,
    payload=claims,
    signer=st.sampled_from([MATCHING, MATCHING, SECRET, *PRIVATE_KEYS.values()]),
)
def test_a_crafted_header_or_claim_is_refused_as_unauthenticated(
    authenticator: Authenticator, header: dict[str, Any], payload: Any, signer: Any
) -> None:
    if signer is MATCHING:
        kid = header.get("kid")
        signer = PRIVATE_KEYS.get(kid, SECRET) if isinstance(kid, str) else SECRET
    check(authenticator, signed(header, payload, signer))


@settings(max_examples=300, deadline=None)
@given(token=st.text(max_size=200) | st.lists(st.text(max_size=40), min_size=1, max_size=5).map(".".join))
def test_text_that_is_not_a_token_is_refused_as_unauthenticated(
    authenticator: Authenticator, token: str
) -> None:
    assert check(authenticator, token) is None


@pytest.mark.parametrize(
    ("header", "payload", "signer", "why"),
    [
        # The header names a key of another kind: the library would raise TypeError with it.
        ({"alg": "ES256", "kid": "rsa"}, {}, PRIVATE_KEYS["p256"], "key 'rsa' is not a key for ES256"),
        ({"alg": "ES256", "kid": "p384"}, {}, PRIVATE_KEYS["p256"], "key 'p384' is not a key for ES256"),
        ({"alg": "RS256", "kid": "ed"}, {}, PRIVATE_KEYS["rsa"], "key 'ed' is not a key for RS256"),
        ({"alg": "EdDSA", "kid": "p256"}, {}, PRIVATE_KEYS["ed"], "key 'p256' is not a key for EdDSA"),
        # Validly signed, with a scope that is a list of other things than text.
        ({"alg": "HS256"}, {"scope": [1, 2]}, SECRET, "scope claim must be text or a list of texts"),
        ({"alg": "ES256", "kid": "p256"}, {"scope": [None]}, PRIVATE_KEYS["p256"], "scope claim"),
        ({"alg": "HS256"}, {"scope": {"read": "*"}}, SECRET, "scope claim must be text"),
    ],
)
def test_the_crafted_tokens_once_answered_internal_are_refused_naming_why(
    authenticator: Authenticator, header: dict[str, Any], payload: dict[str, Any], signer: Any, why: str
) -> None:
    good = {"sub": "alice", "exp": int(time.time()) + 86_400, "iss": "lab", "aud": "gw1"}
    with pytest.raises(Unauthenticated, match="bearer token refused") as refused:
        authenticator.subject_of_token(signed(header, {**good, **payload}, signer))
    assert why in refused.value.message


def test_a_good_token_of_every_key_kind_still_names_its_subject(authenticator: Authenticator) -> None:
    good = {"sub": "alice", "exp": int(time.time()) + 86_400, "iss": "lab", "aud": "gw1", "scope": ["read:*"]}
    for kid, algorithm in (("rsa", "PS256"), ("p256", "ES256"), ("p384", "ES384"), ("ed", "EdDSA")):
        token = signed({"alg": algorithm, "kid": kid}, good, PRIVATE_KEYS[kid])
        subject = authenticator.subject_of_token(token)
        assert subject.name == "alice" and subject.via == "token"
    assert authenticator.subject_of_token(jwt.encode(good, SECRET, algorithm="HS384")).name == "alice"
