"""The JSON routes: services, a service's model, Get (with wildcards), Set, health.

A binary value is JSON ``{"data": BASE64, "media_type": TYPE}`` where text is ``{"value": TEXT}``;
``?raw=1`` (or ``Accept`` naming the media type) reads its bytes, and a Set with the property's
media type (or ``application/octet-stream``) as its content type writes them
(:mod:`gateway.fronts.http.binary`).

Every call goes through the gateway's one call layer (:class:`gateway.engine.calls.Calls`), in the
engine's own types (:mod:`gateway.engine.types`): the same router, time limits, rules, audit and
size checks as a gRPC Get, Set or Describe.
"""

from __future__ import annotations

import json
from typing import Any

from aiohttp import web

from gateway.config import REGISTRY_NAME
from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.rules import Operation, Subject
from gateway.engine.sizes import MAX_BINARY_SIZE
from gateway.engine.types import DescribeCall, GetCall, PropertyRef, SetCall, is_snapshot
from gateway.fronts.http.binary import (
    OCTET_STREAM,
    RAW_KEY,
    MediaTypes,
    accepts_raw,
    essence,
    property_model,
    raw_asked,
    raw_response,
    text_response,
    value_json,
)
from gateway.fronts.http.bodies import BodyTooLarge, SetBody, parse_set_body, query_parameters, read_body
from gateway.fronts.http.errors import PAYLOAD_TOO_LARGE, error_response
from gateway.fronts.http.safety import JSON_TYPE, identify
from services.kernel.backend import NO_PARAMS
from services.kernel.errors import InvalidArgument, NotFound, PropertyError, ResourceExhausted
from services.kernel.model import Access, ParameterModel, PropertyModel, ServiceModel
from services.kernel.paths import WILDCARD
from services.kernel.values import Value, ValueFormatError, parse_names, parse_vector

#: The registry's columns /api/v1/services reads, each with one wildcard Get.
_COLUMNS = ("type", "url", "state", "location")


def json_response(data: Any, status: int = 200) -> web.Response:
    """``data`` as a JSON answer that no cache keeps (values change)."""
    return web.Response(
        status=status,
        text=json.dumps(data, ensure_ascii=False),
        content_type="application/json",
        headers={"Cache-Control": "no-store"},
    )


def _or_none(text: str) -> str | None:
    return text or None


def parameter_json(p: ParameterModel) -> dict[str, Any]:
    return {
        "name": p.name,
        "type": p.type,
        "required": p.required,
        "default": _or_none(p.default),
        "doc": _or_none(p.doc),
    }


def property_json(p: PropertyModel) -> dict[str, Any]:
    return {
        "name": p.name,
        "type": p.type,
        "access": p.access.value,
        "unit": _or_none(p.unit),
        "minimum": p.minimum,
        "maximum": p.maximum,
        "choices": list(p.choices) or None,
        "length": p.length,
        "gui": _or_none(p.gui),
        "doc": _or_none(p.doc),
        "media_type": _or_none(p.media_type),
        "max_size": (p.max_size or MAX_BINARY_SIZE) if p.type == "bytes" else None,
        "resolution": p.resolution,
        "value": parameter_json(p.value) if p.value is not None else None,
        "parameters": [parameter_json(q) for q in p.parameters],
    }


def model_json(service: str, model: ServiceModel) -> dict[str, Any]:
    """The Describe model as JSON: unset fields are null."""
    return {
        "service": service,
        "type": model.type,
        "doc": _or_none(model.doc),
        "properties": [property_json(p) for p in model.properties],
    }


def location_json(text: str) -> list[float] | None:
    """A registry location (``(1 2 0 0 0 0)``) as numbers; None when it has none (``()``)."""
    try:
        vector = parse_vector(text)
    except PropertyError:
        return None
    return [float(x) for x in vector] or None


class Api:
    """The JSON route handlers; see the module docstring."""

    def __init__(self, calls: Calls, guard: Guard, max_body: int) -> None:
        self.calls = calls
        self.guard = guard
        self.max_body = max_body

    def _service(self, request: web.Request) -> str:
        service = request.match_info["service"]
        if service == WILDCARD:
            raise InvalidArgument("service '*' is allowed only in /api/v1/events selectors")
        return service

    async def health(self, request: web.Request) -> web.Response:
        return json_response({"status": "ok"})

    async def _names_page(self, after: str, limit: str, subject: Subject) -> list[str]:
        """One page of the registry's ``service_names``: after ``after``, at most ``limit`` ("": 1,000)."""
        parameters = {"after": after, **({"limit": limit} if limit else {})}
        asked = GetCall(REGISTRY_NAME, "service_names", parameters)
        return parse_names(_text((await self.calls.get(asked, self.calls.timeout, subject)).value))

    async def _columns(self, names: list[str], subject: Subject) -> dict[str, dict[str, str]]:
        """``services.NAME.COLUMN`` of each name, in Gets of many paths (``max_get_paths`` each):
        a wildcard Get would count every registration, past the limit in a big registry. A Get
        that meets a service that left meanwhile is read again path by path, the rest kept."""
        paths = [(name, column) for name in names for column in _COLUMNS]
        per_get = max(1, self.calls.max_get_paths)
        found: dict[str, dict[str, str]] = {}
        for start in range(0, len(paths), per_get):
            chunk = paths[start : start + per_get]
            refs = [PropertyRef("", f"services.{name}.{column}") for name, column in chunk]
            asked = GetCall(REGISTRY_NAME, refs[0].path, more=refs[1:])
            try:
                answer = await self.calls.get(asked, self.calls.timeout, subject)
                values: list[str | None] = [_text(answer.value), *(_text(item.value) for item in answer.more)]
            except NotFound:
                values = [await self._column(name, column, subject) for name, column in chunk]
            for (name, column), value in zip(chunk, values, strict=True):
                if value is not None:
                    found.setdefault(name, {})[column] = value
        return found

    async def _column(self, name: str, column: str, subject: Subject) -> str | None:
        asked = GetCall(REGISTRY_NAME, f"services.{name}.{column}")
        try:
            return _text((await self.calls.get(asked, self.calls.timeout, subject)).value)
        except NotFound:
            return None  # it left

    async def services(self, request: web.Request) -> web.Response:
        """Every service the registry knows, in the order they joined, with its columns; with
        ``?limit=N`` (and ``&after=NAME``), one page of them in name order and ``next``, the
        ``after`` of the page that follows (an empty page: no more). A registry whose ``services``
        passes one value's 64 KiB (about 6,000 names) is listed whole in name order."""
        subject = identify(request, self.guard)
        timeout = self.calls.timeout
        after, limit = request.query.get("after", ""), request.query.get("limit", "")
        paged = "after" in request.query or "limit" in request.query
        if paged:
            names = await self._names_page(after, limit, subject)
        else:
            listing = await self.calls.get(GetCall(REGISTRY_NAME, "services"), timeout, subject)
            try:
                names = parse_names(_text(listing.value))
            except ValueFormatError:  # past one value: read it a page at a time
                names = []
                while page := await self._names_page(names[-1] if names else "", "", subject):
                    names += page
        columns = await self._columns(names, subject)
        services = []
        for name in names:
            row = columns.get(name, {})
            services.append(
                {
                    "name": name,
                    "type": row.get("type", "unknown"),
                    "state": row.get("state", "unknown"),
                    "address": row.get("url", ""),
                    "location": location_json(row.get("location", "")),
                }
            )
        if paged:
            return json_response({"services": services, "next": names[-1] if names else None})
        return json_response({"services": services})

    async def model(self, request: web.Request) -> web.Response:
        service = self._service(request)
        subject = identify(request, self.guard)
        model = await self.calls.describe(DescribeCall(service), self.calls.timeout, subject)
        return json_response(model_json(service, model))

    async def get(self, request: web.Request) -> web.Response:
        service = self._service(request)
        path = request.match_info["path"]
        raw = raw_asked(request.query)
        subject = identify(request, self.guard)
        parameters = query_parameters(request.query, ignore=(RAW_KEY,))
        get = GetCall(service, path, parameters)
        answer = await self.calls.get(get, self.calls.timeout, subject)
        if is_snapshot(get):
            if raw:
                raise InvalidArgument("raw=1 reads one property: a path with '*' answers JSON only")
            media_types = MediaTypes(self.calls)
            values = []
            for item in answer.more:
                item_time = {"time": item.time_ns / 1e9}
                if isinstance(item.value, str):
                    values.append({"path": item.path, **value_json(item.value, None, ""), **item_time})
                    continue
                media_type = await media_types.of(service, item.path)
                values.append({"path": item.path, **value_json("", item.value, media_type), **item_time})
            return json_response({"service": service, "path": path, "values": values})
        value = answer.value
        # The value's source time, in seconds since the epoch, as an event's ``time``.
        when = answer.time_ns / 1e9
        if isinstance(value, str):
            if raw:
                return text_response(value)
            return json_response({"service": service, "path": path, "value": value, "time": when})
        media_type = await MediaTypes(self.calls).of(service, path)
        if raw or accepts_raw(request, media_type):
            return raw_response(value, media_type)
        return json_response(
            {"service": service, "path": path, **value_json("", value, media_type), "time": when}
        )

    async def set(self, request: web.Request) -> web.Response:
        service = self._service(request)
        path = request.match_info["path"]
        # Identified even when nothing is refused: the audit trail names who set what.
        subject = identify(request, self.guard, always=True)
        binary: PropertyModel | None = None
        if request.content_type == JSON_TYPE:
            raw = await read_body(request, self.max_body, "http.max_body")
            if request.query_string:
                raise InvalidArgument('a Set takes its request parameters in the body: {"parameters": {...}}')
            body = parse_set_body(raw)
            if isinstance(body.value, bytes):
                binary = await self._binary_property(service, path, subject)
                _check_size(service, binary, len(body.value))
        else:
            # The raw bytes of a binary property: its media type (or octet-stream) says so, and
            # the request parameters come in the query string (there is no JSON to carry them).
            binary = await self._binary_property(service, path, subject, request.content_type)
            data = await read_body(request, max_size(binary), f"the max_size of {service}/{path}")
            body = SetBody(data, query_parameters(request.query))
        set_call = SetCall(service, path, body.value, body.parameters or NO_PARAMS)
        answer = await self.calls.set(set_call, self.calls.timeout, subject)
        if isinstance(answer, str):
            return json_response({"service": service, "path": path, "value": answer})
        media_type = binary.media_type if binary is not None else ""
        if not media_type:
            media_type = await MediaTypes(self.calls).of(service, path)
        return json_response({"service": service, "path": path, **value_json("", answer, media_type)})

    async def raw_limit(self, request: web.Request) -> int | None:
        """The most bytes a raw Set of the request's property may carry; None when that is not known
        (a caller who may not set it, no such property, not binary, a model that cannot be read:
        the Set itself says why)."""
        service = request.match_info.get("service", "")
        path = request.match_info.get("path", "")
        try:
            if not self._may_set(identify(request, self.guard, always=True), service, path):
                return None
            prop = await property_model(self.calls, service, path)
        except PropertyError:
            return None
        return max_size(prop) if takes_bytes(prop) else None

    def _may_set(self, subject: Subject, service: str, path: str) -> bool:
        """Whether the rules let ``subject`` write ``path`` or invoke it (the model tells which it is)."""
        guard = self.guard
        return guard.may(subject, service, path, Operation.WRITE) or guard.may(
            subject, service, path, Operation.INVOKE
        )

    async def _binary_property(
        self, service: str, path: str, subject: Subject, content_type: str | None = None
    ) -> PropertyModel:
        """The model of ``path``, a binary property; InvalidArgument when it is not one, or when
        ``content_type`` (a raw Set's) is neither its media type nor application/octet-stream (any
        type will do for a property whose media type is application/octet-stream)."""
        if not self._may_set(subject, service, path):
            self.guard.require(subject, service, path, Operation.WRITE)  # refused, named and audited
        prop = await property_model(self.calls, service, path)
        if not takes_bytes(prop):
            kind = prop.value.type if prop.value is not None else prop.type
            raise InvalidArgument(
                f"{service}/{path} is not a binary property (it takes {kind}): send"
                f' Content-Type: {JSON_TYPE} with {{"value": TEXT}}'
            )
        media_type = essence(prop.media_type or OCTET_STREAM)
        # A property of any bytes (application/octet-stream: a store of files) takes them under
        # any type; the types a form can send never get here (gateway.fronts.http.safety).
        if (
            content_type is not None
            and media_type != OCTET_STREAM
            and content_type not in (media_type, OCTET_STREAM)
        ):
            raise InvalidArgument(
                f"a Set of {service}/{path} takes Content-Type: {media_type} or {OCTET_STREAM} (its raw"
                f' bytes), or {JSON_TYPE} ({{"data": BASE64}}), not {content_type[:100]!r}'
            )
        return prop


def _text(value: Value) -> str:
    """A registry value as text (the registry's values are text; bytes would be a bug there)."""
    return value if isinstance(value, str) else value.decode(errors="replace")


def takes_bytes(prop: PropertyModel) -> bool:
    """Whether a Set of ``prop`` carries bytes: a binary property, or an action or query whose value is."""
    if prop.access in (Access.ACTION, Access.QUERY):
        return prop.value is not None and prop.value.type == "bytes"
    return prop.type == "bytes"


def max_size(prop: PropertyModel) -> int:
    """The most bytes a Set of binary ``prop`` may carry (its own bound, else the gateway's)."""
    return prop.max_size or MAX_BINARY_SIZE


def _check_size(service: str, prop: PropertyModel, size: int) -> None:
    limit = max_size(prop)
    if size > limit:
        raise BodyTooLarge(
            f"{service}/{prop.name}: the value is {size} bytes, more than its max_size ({limit} bytes)"
        )


def body_too_large(length: int | None, limit: int, bound: str = "http.max_body") -> web.Response:
    """413 RESOURCE_EXHAUSTED for a body of ``length`` bytes (None: found while reading it)."""
    size = f"{length} bytes, " if length is not None else ""
    err = ResourceExhausted(f"the request body is {size}more than {bound} ({limit} bytes)")
    return error_response(err, status=PAYLOAD_TOO_LARGE)
