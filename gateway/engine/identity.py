"""Who is calling: a gRPC caller's :class:`~gateway.engine.rules.Subject` from its certificate or its token.

* **Client certificate** (mutual TLS): the subject is the certificate's
  common name, or its first subject alternative name when it has none, as
  grpc's ``auth_context()`` reports them (``x509_common_name``,
  ``x509_subject_alternative_name``).
* **Bearer token**: ``authorization: Bearer JWT`` in the call's metadata, a
  JWT checked with PyJWT against ``[auth] jwt_secret_file`` (HS256/384/512)
  or ``[auth] jwks_file`` (RS*, PS*, ES*, EdDSA; the key is picked by the
  token's ``kid``), with its expiry (``exp`` is required), and with
  ``[auth] issuer`` and ``audience`` when the config names them. The
  subject is the ``sub`` claim; a ``scope`` claim narrows what the rules
  allow (:class:`~gateway.engine.rules.Scopes`). A token wins over a certificate.

A token that is bad, expired or for someone else is UNAUTHENTICATED naming
why. Without ``[auth]`` a token is not looked at (the gateway behaves as it
did before tokens). A caller with neither is :data:`ANONYMOUS`.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jwt
from cryptography.hazmat.primitives.asymmetric import ec, ed448, ed25519, rsa

from gateway.engine.rules import ANONYMOUS_NAME, Scopes, Subject
from services.kernel.errors import InvalidArgument, Unauthenticated

ANONYMOUS = Subject(ANONYMOUS_NAME)
#: Algorithms accepted with a shared secret; a JWKS key's own algorithm family is used otherwise.
_SECRET_ALGORITHMS = ("HS256", "HS384", "HS512")
_KEY_ALGORITHMS = ("RS256", "RS384", "RS512", "PS256", "PS384", "PS512", "ES256", "ES384", "ES512", "EdDSA")
#: The kind of key each JWKS algorithm verifies with (and, for ECDSA, its curve): a token's ``alg``
#: is its author's word, so a ``kid`` naming a key of another kind is a refusal, not a call into
#: the library with a key it cannot use (which raises TypeError rather than a token error).
_KEY_KINDS: dict[str, tuple[type, ...]] = {
    **dict.fromkeys(("RS256", "RS384", "RS512", "PS256", "PS384", "PS512"), (rsa.RSAPublicKey,)),
    **dict.fromkeys(("ES256", "ES384", "ES512"), (ec.EllipticCurvePublicKey,)),
    "EdDSA": (ed25519.Ed25519PublicKey, ed448.Ed448PublicKey),
}
_CURVES = {"ES256": ec.SECP256R1.name, "ES384": ec.SECP384R1.name, "ES512": ec.SECP521R1.name}
_BEARER = "bearer "
#: Seconds of clock difference tolerated on ``exp`` and ``nbf``.
_LEEWAY_S = 5.0


@dataclass(frozen=True, slots=True)
class AuthSection:
    """``[auth]``: how bearer tokens are checked. All empty = tokens are not looked at."""

    #: File holding the shared secret of HS256 tokens (its text, surrounding whitespace dropped).
    jwt_secret_file: str = ""
    #: File holding a JSON Web Key Set of the keys that sign RS/ES/PS/EdDSA tokens.
    jwks_file: str = ""
    #: When set, a token's ``iss`` must be this.
    issuer: str = ""
    #: When set, a token's ``aud`` must name this.
    audience: str = ""

    @property
    def configured(self) -> bool:
        return bool(self.jwt_secret_file or self.jwks_file)


def _text(values: Sequence[bytes] | None) -> str:
    return values[0].decode("utf-8", "replace") if values else ""


def certificate_subject(auth_context: Mapping[str, Sequence[bytes]]) -> Subject | None:
    """The subject a client certificate proves (its CN, else its first SAN); None without one."""
    name = _text(auth_context.get("x509_common_name")) or _text(
        auth_context.get("x509_subject_alternative_name")
    )
    return Subject(name, authenticated=True, via="certificate") if name else None


def bearer_token(metadata: Iterable[tuple[str, str | bytes]] | None) -> str | None:
    """The token of an ``authorization: Bearer ...`` entry of the metadata; None without one."""
    for key, value in metadata or ():
        if key == "authorization" and isinstance(value, str):
            if not value.lower().startswith(_BEARER):
                raise Unauthenticated("the authorization metadata must be 'Bearer TOKEN'")
            return value[len(_BEARER) :].strip()
    return None


class Authenticator:
    """Checks tokens as ``[auth]`` says and names callers; see the module docstring."""

    def __init__(self, section: AuthSection) -> None:
        """Reads the key files now; InvalidArgument naming the file when one cannot be used."""
        self.section = section
        self._secret: str | None = None
        self._keys: dict[str, Any] = {}
        if section.jwt_secret_file:
            self._secret = _read(section.jwt_secret_file, "jwt_secret_file").strip()
            if not self._secret:
                raise InvalidArgument(f"auth.jwt_secret_file: {section.jwt_secret_file} is empty")
        if section.jwks_file:
            self._keys = _load_jwks(section.jwks_file)

    @property
    def checks_tokens(self) -> bool:
        return self.section.configured

    def identify(
        self, metadata: Iterable[tuple[str, str | bytes]] | None, auth_context: Mapping[str, Sequence[bytes]]
    ) -> Subject:
        """The caller's subject; Unauthenticated for a token that does not check out."""
        if self.checks_tokens:
            token = bearer_token(metadata)
            if token is not None:
                return self.subject_of_token(token)
        return certificate_subject(auth_context) or ANONYMOUS

    def subject_of_token(self, token: str) -> Subject:
        """The subject a JWT proves; Unauthenticated naming why it is refused."""
        section = self.section
        try:
            header = jwt.get_unverified_header(token)
            algorithm = str(header.get("alg", ""))
            if algorithm in _SECRET_ALGORITHMS and self._secret is not None:
                key: Any = self._secret
                algorithms = list(_SECRET_ALGORITHMS)
            elif algorithm in _KEY_ALGORITHMS and self._keys:
                key = self._key_for(header.get("kid"), algorithm)
                algorithms = [algorithm]
            else:
                raise Unauthenticated(f"bearer token refused: algorithm {algorithm!r} is not accepted here")
            claims = jwt.decode(
                token,
                key,
                algorithms=algorithms,
                issuer=section.issuer or None,
                audience=section.audience or None,
                leeway=_LEEWAY_S,
                options={"require": ["exp", "sub"], "verify_aud": bool(section.audience)},
            )
        except jwt.PyJWTError as exc:
            raise Unauthenticated(f"bearer token refused: {exc}") from None
        subject = claims.get("sub")
        if not isinstance(subject, str) or not subject:
            raise Unauthenticated("bearer token refused: its sub claim must name the caller")
        scopes = None
        if "scope" in claims:
            scope = claims["scope"]
            if isinstance(scope, list) and all(isinstance(word, str) for word in scope):
                scope = " ".join(scope)
            if not isinstance(scope, str):
                raise Unauthenticated("bearer token refused: its scope claim must be text or a list of texts")
            try:
                scopes = Scopes.parse(scope)
            except InvalidArgument as exc:
                raise Unauthenticated(f"bearer token refused: {exc.message}") from None
        return Subject(subject, authenticated=True, scopes=scopes, via="token")

    def _key_for(self, kid: object, algorithm: str) -> Any:
        """The JWKS key ``kid`` names, when it is of the kind ``algorithm`` verifies with."""
        if isinstance(kid, str) and kid in self._keys:
            key = self._keys[kid]
        elif kid is None and len(self._keys) == 1:
            key = next(iter(self._keys.values()))
        else:
            raise Unauthenticated(f"bearer token refused: no key {kid!r} in auth.jwks_file")
        suits = isinstance(key, _KEY_KINDS[algorithm])
        if suits and algorithm in _CURVES:
            suits = key.curve.name == _CURVES[algorithm]
        if not suits:
            raise Unauthenticated(f"bearer token refused: key {kid!r} is not a key for {algorithm}")
        return key


def _read(path: str, key: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InvalidArgument(f"auth.{key}: cannot read {path}: {exc.strerror or exc}") from None


def _load_jwks(path: str) -> dict[str, Any]:
    """The keys of a JWKS file by ``kid`` (a key without one is "")."""
    text = _read(path, "jwks_file")
    try:
        keys = jwt.PyJWKSet.from_dict(json.loads(text)).keys
    except (ValueError, jwt.PyJWTError) as exc:
        raise InvalidArgument(f"auth.jwks_file: {path} is not a usable JSON Web Key Set: {exc}") from None
    # A private key in the file verifies as its public half (the kinds in _KEY_KINDS are public).
    return {key.key_id or "": _public(key.key) for key in keys}


_PRIVATE_KEYS = (
    rsa.RSAPrivateKey,
    ec.EllipticCurvePrivateKey,
    ed25519.Ed25519PrivateKey,
    ed448.Ed448PrivateKey,
)


def _public(key: Any) -> Any:
    return key.public_key() if isinstance(key, _PRIVATE_KEYS) else key
