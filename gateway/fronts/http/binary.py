"""Binary values over HTTP: base64 in JSON, the raw bytes on request, and their media types.

In JSON a binary value is ``{"data": BASE64, "media_type": "image/png"}`` where a text value is
``{"value": TEXT}`` (standard base64, RFC 4648 section 4, with padding). ``?raw=1``, or an
``Accept`` header that names the property's media type or ``application/octet-stream``, answers
the bytes themselves.

The media type comes from the service's model (Describe's ``media_type``); a value is not labelled
with it on the wire. A raw answer is served with that type only when a browser cannot run it:
``text/html`` or ``image/svg+xml`` from a service would otherwise be a page of the console's own
origin, able to call every route with the operator's token. Anything else is served as
``application/octet-stream``, every raw answer with ``X-Content-Type-Options: nosniff`` and
``Content-Security-Policy: sandbox`` (a sandboxed document runs no script even if a browser
renders it).
"""

from __future__ import annotations

import base64
import binascii
import logging
import re
from collections.abc import Iterable
from typing import Any

from aiohttp import hdrs, web

from gateway.engine.calls import Calls
from gateway.engine.router import bounded_call
from services.kernel.errors import InvalidArgument, NotFound, PropertyError
from services.kernel.model import PropertyModel, ServiceModel

log = logging.getLogger(__name__)

#: What a binary value is when its model does not say.
OCTET_STREAM = "application/octet-stream"
#: The query key of a raw read (``?raw=1``); it is not passed on as a request parameter.
RAW_KEY = "raw"
_RAW_WORDS = {"1": True, "true": True, "0": False, "false": False}
#: Families of media types a browser shows but never runs, and single types of the same kind.
_INERT_FAMILIES = ("image", "audio", "video")
_INERT_TYPES = frozenset({OCTET_STREAM, "application/x-npy", "application/json", "application/cbor"})
_RUNNABLE = frozenset({"image/svg+xml"})
_ESSENCE = re.compile(r"^[a-z0-9][a-z0-9!#$&^_.+-]{0,126}/[a-z0-9][a-z0-9!#$&^_.+-]{0,126}$")
#: Headers of every raw answer: no sniffing, no script, no cache (values change).
RAW_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "Content-Security-Policy": "sandbox; default-src 'none'",
    hdrs.CACHE_CONTROL: "no-store",
}


def essence(media_type: str) -> str:
    """``image/png`` of ``Image/PNG; q=1``: the type without parameters, lower case."""
    return media_type.split(";", 1)[0].strip().lower()


def served_type(media_type: str) -> str:
    """The Content-Type a raw answer carries for a value of ``media_type`` (see the module docstring)."""
    kind = essence(media_type)
    if not _ESSENCE.match(kind) or kind in _RUNNABLE:
        return OCTET_STREAM
    if kind in _INERT_TYPES or kind.split("/", 1)[0] in _INERT_FAMILIES:
        return kind
    return OCTET_STREAM


def encode_data(data: bytes) -> str:
    """Standard base64 with padding, as JSON carries a binary value."""
    return base64.b64encode(data).decode("ascii")


def decode_data(text: Any, where: str = "'data'") -> bytes:
    """The bytes of a JSON ``data`` (standard base64 with padding); InvalidArgument naming what is wrong."""
    if not isinstance(text, str):
        raise InvalidArgument(
            f"{where} must be a string of standard base64 (RFC 4648), not {type(text).__name__}"
        )
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InvalidArgument(
            f"{where} is not standard base64 (RFC 4648: A-Z a-z 0-9 + /, '=' padding, no line breaks): {exc}"
        ) from None


def value_json(value: str, data: bytes | None, media_type: str) -> dict[str, str]:
    """``{"value": TEXT}``, or ``{"data": BASE64, "media_type": TYPE}`` for a binary value."""
    if data is None:
        return {"value": value}
    return {"data": encode_data(data), "media_type": media_type or OCTET_STREAM}


def raw_asked(query: Any) -> bool:
    """Whether ``?raw=1`` (or ``true``) asks for the bytes themselves; another word is refused."""
    word = query.get(RAW_KEY)
    if word is None:
        return False
    raw = _RAW_WORDS.get(word.strip().lower())
    if raw is None:
        raise InvalidArgument(f"raw must be 1, true, 0 or false, not {word[:50]!r}")
    return raw


def accepts_raw(request: web.Request, media_type: str) -> bool:
    """Whether the ``Accept`` header names ``media_type`` or ``application/octet-stream`` (not a wildcard:
    a browser's ``*/*`` still gets JSON)."""
    wanted = {essence(kind) for kind in request.headers.get(hdrs.ACCEPT, "").split(",")}
    return essence(media_type or OCTET_STREAM) in wanted or OCTET_STREAM in wanted


def raw_response(data: bytes, media_type: str) -> web.Response:
    """The bytes of a binary value as the whole answer."""
    return web.Response(body=data, content_type=served_type(media_type), headers=RAW_HEADERS)


def text_response(value: str) -> web.Response:
    """A text value as the whole answer (a raw read of a text property)."""
    return web.Response(text=value, content_type="text/plain", charset="utf-8", headers=RAW_HEADERS)


class MediaTypes:
    """The media types of binary properties, read from the services' models (Describe) and kept.

    Each event stream holds one, so that a model is read once per service it sees binary values
    of, not per event; a path its service's model does not list (or a model that cannot be read)
    is ``application/octet-stream``. At most ``limit`` paths are kept (beyond, it starts afresh).
    It is asked only about values the caller has just been allowed to read, so the model is read
    without a rule check of its own.
    """

    def __init__(self, calls: Calls, limit: int = 10_000) -> None:
        self.calls = calls
        self.limit = limit
        self.known: dict[tuple[str, str], str] = {}

    async def of(self, service: str, path: str) -> str:
        """The media type of ``service``'s ``path``."""
        key = (service, path)
        found = self.known.get(key)
        if found is None:
            await self.learn(service)
            found = self.known.setdefault(key, OCTET_STREAM)
        return found

    async def learn(self, service: str) -> None:
        """Read ``service``'s model and keep the media type of each binary property it lists."""
        if len(self.known) >= self.limit:
            self.known.clear()
        try:
            model = await service_model(self.calls, service)
        except PropertyError as exc:
            log.debug("media types of %s unknown: %s", service, exc.message)
            return
        for prop in binary_properties(model.properties):
            self.known[(service, prop.name)] = prop.media_type or OCTET_STREAM


def binary_properties(properties: Iterable[PropertyModel]) -> Iterable[PropertyModel]:
    """The properties of a model whose values are bytes."""
    return (p for p in properties if p.type == "bytes")


async def service_model(calls: Calls, service: str) -> ServiceModel:
    """``service``'s model, read through the router with the call time limit and no rule check:
    the callers check the property itself first (a caller may read ``cam1/frame`` without being
    allowed to read the whole service)."""
    backend = calls.router.backend(service)
    return await bounded_call(backend.describe(), calls.timeout, lambda: f"{service}: describe")


async def property_model(calls: Calls, service: str, path: str) -> PropertyModel:
    """The model of ``service``'s ``path`` (see :func:`service_model`); NotFound when it lists none."""
    model = await service_model(calls, service)
    found = next((p for p in model.properties if p.name == path), None)
    if found is None:
        raise NotFound(f"{service} has no property `{path}` in its model")
    return found
