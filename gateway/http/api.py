"""The JSON routes: services, a service's model, Get (with wildcards), Set, health.

Every call goes through the gateway's one call layer (:class:`gateway.calls.Calls`): the
same router, time limits, rules, audit and size checks as a gRPC Get, Set or Describe.
"""

from __future__ import annotations

import json
from typing import Any

from aiohttp import web

from gateway.calls import Calls, is_snapshot
from gateway.config import REGISTRY_NAME
from gateway.guard import Guard
from gateway.http.bodies import parse_set_body, query_parameters
from gateway.http.errors import PAYLOAD_TOO_LARGE, error_response
from gateway.http.safety import identify
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.errors import InvalidArgument, NotFound, PropertyError, ResourceExhausted
from services.model import ParameterModel, PropertyModel, ServiceModel
from services.paths import WILDCARD
from services.values import parse_names, parse_vector

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

    async def services(self, request: web.Request) -> web.Response:
        """Every service the registry knows, in the order they joined, with its columns."""
        subject = identify(request, self.guard)
        timeout = self.calls.timeout
        listed = pb.GetRequest(service=REGISTRY_NAME, property="services")
        listing = await self.calls.get(listed, timeout, subject)
        names = parse_names(listing.value)
        columns: dict[str, dict[str, str]] = {}
        for column in _COLUMNS:
            pattern = f"services.{WILDCARD}.{column}"
            try:
                answer = await self.calls.get(
                    pb.GetRequest(service=REGISTRY_NAME, property=pattern), timeout, subject
                )
            except NotFound:
                answer = pb.GetResponse()  # nothing matched: no service has the column (yet)
            for item in answer.more:
                name = item.property.split(".")[1]
                columns.setdefault(name, {})[column] = item.value
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
        return json_response({"services": services})

    async def model(self, request: web.Request) -> web.Response:
        service = self._service(request)
        subject = identify(request, self.guard)
        model = await self.calls.describe(service, self.calls.timeout, subject)
        return json_response(model_json(service, model))

    async def get(self, request: web.Request) -> web.Response:
        service = self._service(request)
        path = request.match_info["path"]
        subject = identify(request, self.guard)
        get = pb.GetRequest(service=service, property=path, parameters=query_parameters(request.query))
        answer = await self.calls.get(get, self.calls.timeout, subject)
        if is_snapshot(get):
            values = [{"path": item.property, "value": item.value} for item in answer.more]
            return json_response({"service": service, "path": path, "values": values})
        return json_response({"service": service, "path": path, "value": answer.value})

    async def set(self, request: web.Request) -> web.Response:
        service = self._service(request)
        path = request.match_info["path"]
        length = request.content_length
        if length is not None and length > self.max_body:
            return body_too_large(length, self.max_body)
        try:
            raw = await request.read()
        except web.HTTPRequestEntityTooLarge:
            return body_too_large(None, self.max_body)
        if request.query_string:
            raise InvalidArgument('a Set takes its request parameters in the body: {"parameters": {...}}')
        body = parse_set_body(raw)
        # Identified even when nothing is refused: the audit trail names who set what.
        subject = identify(request, self.guard, always=True)
        set_request = pb.SetRequest(
            service=service, property=path, value=body.value, parameters=body.parameters
        )
        answer = await self.calls.set(set_request, self.calls.timeout, subject)
        return json_response({"service": service, "path": path, "value": answer.value})


def body_too_large(length: int | None, max_body: int) -> web.Response:
    """413 RESOURCE_EXHAUSTED for a body of ``length`` bytes (None: found while reading it)."""
    size = f"{length} bytes, " if length is not None else ""
    err = ResourceExhausted(f"the request body is {size}more than http.max_body ({max_body} bytes)")
    return error_response(err, status=PAYLOAD_TOO_LARGE)
