"""What a browser could be tricked into, refused; and who a request comes from.

* **Origin.** The front end sends no CORS headers, so a page of another origin cannot read
  its answers; a request whose ``Origin`` header names another origin is refused as well
  (403 PERMISSION_DENIED), so such a page cannot make one either (a Set by a form or
  ``fetch`` with ``no-cors``).
* **Content type.** A PUT or POST must name its content type: ``application/json``, or for
  the raw bytes of a binary property its media type or ``application/octet-stream``. The three
  types a plain HTML form (or a ``no-cors`` ``fetch``) can send without a preflight —
  ``text/plain``, ``application/x-www-form-urlencoded``, ``multipart/form-data`` — and a body
  without a type are refused, so every accepted Set is one a cross-origin page could only make
  after a preflight, which is never answered (no CORS headers).
* **Host.** When the front end listens on a loopback address, a ``Host`` that is not a
  loopback name or address is refused (403): a DNS-rebinding page (``evil.example``
  resolving to 127.0.0.1) reaches the port but never with a loopback host name.
* **Identity** as on the gRPC port: ``Authorization: Bearer TOKEN``, or the cookie
  ``ps_token`` (EventSource cannot set headers; the console sets the cookie with
  SameSite=Strict), or a client certificate over HTTPS; the guard checks it.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping, Sequence
from typing import Any

from aiohttp import hdrs, web

from gateway.engine.guard import Guard
from gateway.engine.identity import ANONYMOUS
from gateway.engine.rules import Subject
from services.kernel.errors import InvalidArgument, PermissionDenied

#: The cookie the console keeps its bearer token in.
TOKEN_COOKIE = "ps_token"
JSON_TYPE = "application/json"
#: The content types a request may carry across origins without a preflight (the CORS-safelisted
#: request-header values of the Fetch standard): what an HTML form can send.
SIMPLE_TYPES = frozenset({"text/plain", "application/x-www-form-urlencoded", "multipart/form-data"})


def is_loopback_host(host: str) -> bool:
    """True for ``localhost``, ``*.localhost`` and loopback addresses, with or without a port."""
    name = host.strip().lower()
    if name.startswith("["):  # [::1]:8080
        name = name[1 : name.find("]")] if "]" in name else name[1:]
    elif name.count(":") == 1:
        name = name.partition(":")[0]
    name = name.rstrip(".")
    if name == "localhost" or name.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def check_request(
    request: web.Request, loopback: bool, routed: bool = True, websocket_origins: frozenset[str] = frozenset()
) -> None:
    """Refuse (PermissionDenied, InvalidArgument) what a browser may have been tricked into sending.

    ``routed``: the request matched a route (else its content type is not judged: 404 or 405 tells more).
    ``websocket_origins``: origins (lower case) whose pages may also open a WebSocket here.
    """
    host = request.headers.get(hdrs.HOST, "")
    if loopback and not is_loopback_host(host):
        raise PermissionDenied(
            f"host {host[:100]!r} is not a loopback name: this front end listens on loopback only"
            " (a page of another site may have pointed its name here)"
        )
    origin = request.headers.get(hdrs.ORIGIN)
    if origin is not None:
        own = f"{request.scheme}://{host}".lower()
        upgrade = request.headers.get(hdrs.UPGRADE, "").lower() == "websocket"
        if origin.lower() != own and not (upgrade and origin.lower() in websocket_origins):
            raise PermissionDenied(
                f"origin {origin[:100]!r} is not this front end's own ({own[:100]!r}): requests from"
                " pages of other origins are refused"
            )
    typed = hdrs.CONTENT_TYPE in request.headers
    if (
        routed
        and request.method in (hdrs.METH_PUT, hdrs.METH_POST)
        and (not typed or request.content_type in SIMPLE_TYPES)
    ):
        given = request.content_type if typed else "none"
        raise InvalidArgument(
            f"a {request.method} needs Content-Type: {JSON_TYPE} (or, with the raw bytes of a binary"
            f" property, its media type or application/octet-stream), not {given!r}"
        )


def certificate_names(peercert: Mapping[str, Any] | None) -> dict[str, Sequence[bytes]]:
    """A verified client certificate (``ssl`` ``getpeercert()``) as grpc's auth context names it."""
    if not peercert:
        return {}
    names: dict[str, Sequence[bytes]] = {}
    for rdn in peercert.get("subject", ()):
        for key, value in rdn:
            if key == "commonName":
                names["x509_common_name"] = [value.encode()]
    sans = [value.encode() for kind, value in peercert.get("subjectAltName", ()) if kind in ("DNS", "URI")]
    if sans:
        names["x509_subject_alternative_name"] = sans
    return names


def identify(request: web.Request, guard: Guard, always: bool = False) -> Subject:
    """Who sends ``request``; ANONYMOUS without a check to make (unless ``always``: a Set is audited)."""
    if not (always or guard.checks):
        return ANONYMOUS
    header = request.headers.get(hdrs.AUTHORIZATION)
    if header is None:
        cookie = request.cookies.get(TOKEN_COOKIE)
        header = f"Bearer {cookie}" if cookie else None
    metadata = [("authorization", header)] if header is not None else []
    peercert = request.transport.get_extra_info("peercert") if request.transport is not None else None
    return guard.identify(metadata, certificate_names(peercert))
