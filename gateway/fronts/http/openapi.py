"""The OpenAPI 3.1 document of the HTTP front end, served at ``/api/v1/openapi.json``.

Written by hand beside the routes (``gateway.fronts.http.front.routes``); a unit test checks that
every route the application serves is described here and that nothing else is.
"""

from __future__ import annotations

from typing import Any

_ERROR = {"$ref": "#/components/responses/Error"}
_SERVICE = {
    "name": "service",
    "in": "path",
    "required": True,
    "description": "The service's registry name (URL-encoded); `*` is not allowed here.",
    "schema": {"type": "string", "pattern": "^[A-Za-z0-9_-]{1,64}$"},
}
_PATH = {
    "name": "path",
    "in": "path",
    "required": True,
    "description": "Dotted property path (URL-encoded); a `*` segment makes a Get a wildcard snapshot.",
    "schema": {"type": "string", "maxLength": 256},
}
_NULLABLE_TEXT = {"type": ["string", "null"]}
_JSON_VALUE = {
    "description": "Value text of the value grammar; a number, boolean or array is formatted into it.",
    "oneOf": [{"type": "string"}, {"type": "number"}, {"type": "boolean"}, {"type": "array"}],
}


def _json(schema: dict[str, Any], description: str) -> dict[str, Any]:
    return {"description": description, "content": {"application/json": {"schema": schema}}}


def _errors(*codes: str) -> dict[str, Any]:
    return {code: _ERROR for code in codes}


_BINARY = {"type": "string", "format": "binary"}
_BASE64 = {
    "type": "string",
    "contentEncoding": "base64",
    "description": "The bytes of a binary value, standard base64 (RFC 4648, with padding).",
}
_SET = {
    "summary": "Set a property (or invoke an action)",
    "description": (
        'JSON `{"value": TEXT}` for a text property, `{"data": BASE64}` for a binary one; or the'
        " raw bytes of a binary value as the body, with the property's media type or"
        " `application/octet-stream` as its content type and the request parameters in the query"
        " string. A body over `http.max_body` (JSON) or the property's `max_size` (bytes) is 413."
    ),
    "parameters": [
        _SERVICE,
        _PATH,
        {
            "name": "parameters",
            "in": "query",
            "description": "A raw Set's request parameters (a JSON Set carries them in its body).",
            "schema": {"type": "object", "additionalProperties": {"type": "string"}},
            "style": "form",
            "explode": True,
        },
    ],
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "schema": {
                    "type": "object",
                    "additionalProperties": False,
                    "oneOf": [{"required": ["value"]}, {"required": ["data"]}],
                    "properties": {
                        "value": _JSON_VALUE,
                        "data": _BASE64,
                        "parameters": {"type": "object", "additionalProperties": _JSON_VALUE},
                    },
                },
                "example": {"value": "<marker><location>(2 1 0 0 0 0)</location></marker>"},
            },
            "application/octet-stream": {
                "schema": {"type": "string", "format": "binary"},
                "description": "The raw bytes of a binary value (or with the property's media type).",
            },
        },
    },
    "responses": {
        "200": _json({"$ref": "#/components/schemas/Value"}, "The service's answer"),
        **_errors("400", "401", "403", "404", "409", "413", "429", "500", "503", "504"),
    },
}

DOCUMENT: dict[str, Any] = {
    "openapi": "3.1.0",
    "info": {
        "title": "Property Service gateway: HTTP/JSON and Server-Sent Events",
        "version": "1",
        "description": (
            "Get, Set and Listen on every service of the gateway, through the same router, rules and"
            " limits as the gRPC contract propertyservice.v1. Errors are"
            ' `{"error": {"code": "NOT_FOUND", "message": "..."}}` with the gRPC code name.'
        ),
    },
    "paths": {
        "/api/v1/services": {
            "get": {
                "summary": "The services the registry knows",
                "parameters": [
                    {
                        "name": "limit",
                        "in": "query",
                        "description": "One page of at most this many services, in name order (1 to 10000)",
                        "schema": {"type": "integer", "minimum": 1, "maximum": 10000},
                    },
                    {
                        "name": "after",
                        "in": "query",
                        "description": "The page after this name (the previous page's `next`)",
                        "schema": {"type": "string"},
                    },
                ],
                "responses": {
                    "200": _json(
                        {"$ref": "#/components/schemas/Services"},
                        "Every service, joining order; with limit or after, a page in name order",
                    ),
                    **_errors("401", "403", "500", "503"),
                },
            }
        },
        "/api/v1/services/{service}/model": {
            "get": {
                "summary": "The service's model (Describe): every property with type, access, unit, range",
                "parameters": [_SERVICE],
                "responses": {
                    "200": _json({"$ref": "#/components/schemas/Model"}, "The model"),
                    **_errors("400", "401", "403", "404", "503", "504"),
                },
            }
        },
        "/api/v1/services/{service}/properties/{path}": {
            "get": {
                "summary": "Get a property; a path with `*` segments is a snapshot of every match",
                "parameters": [
                    _SERVICE,
                    _PATH,
                    {
                        "name": "raw",
                        "in": "query",
                        "description": (
                            "`1`: answer the value itself, a binary one as its bytes with its media type"
                            " (also when `Accept` names that type or `application/octet-stream`), a text"
                            " one as `text/plain`."
                        ),
                        "schema": {"enum": ["1", "true", "0", "false"]},
                    },
                    {
                        "name": "parameters",
                        "in": "query",
                        "description": "Request parameters, e.g. `?frame=robot`.",
                        "schema": {"type": "object", "additionalProperties": {"type": "string"}},
                        "style": "form",
                        "explode": True,
                    },
                ],
                "responses": {
                    "200": {
                        "description": "The value, or every match of a wildcard path; `raw`: the value",
                        "content": {
                            "application/json": {
                                "schema": {
                                    "oneOf": [
                                        {"$ref": "#/components/schemas/Value"},
                                        {"$ref": "#/components/schemas/Snapshot"},
                                    ]
                                }
                            },
                            "application/octet-stream": {"schema": _BINARY},
                            "image/*": {"schema": _BINARY},
                            "text/plain": {"schema": {"type": "string"}},
                        },
                    },
                    **_errors("400", "401", "403", "404", "429", "500", "503", "504"),
                },
            },
            "put": _SET,
            "post": _SET,
        },
        "/api/v1/services/{service}/properties/{path}/history": {
            "get": {
                "summary": "The kept values of a property (or of every match), oldest first",
                "description": (
                    "What the gateway kept of the `[history]` selectors (and, further back, its"
                    " recordings): the same events as `/api/v1/events` sends, each with its"
                    " `sequence` and its source `time`. Refused as a Get is (`read`); a wildcard"
                    " skips what the caller may not read. With more than `limit` in the range, the"
                    " oldest are answered and `truncated` is true: ask again from the last `time`."
                ),
                "parameters": [
                    {**_SERVICE, "description": "The service's registry name, or `*` for every service."},
                    _PATH,
                    {
                        "name": "since",
                        "in": "query",
                        "description": (
                            "From this time on: seconds since the epoch, ISO-8601, or a duration"
                            " before now (`60s`, `5m`, `2h`); unset: from the oldest kept."
                        ),
                        "schema": {"type": "string"},
                    },
                    {
                        "name": "until",
                        "in": "query",
                        "description": "Before this time (the same forms); unset: up to now.",
                        "schema": {"type": "string"},
                    },
                    {
                        "name": "limit",
                        "in": "query",
                        "description": "Most events answered; 0 or unset: `[history] default_limit`.",
                        "schema": {"type": "integer", "minimum": 0},
                    },
                ],
                "responses": {
                    "200": _json({"$ref": "#/components/schemas/History"}, "The kept events"),
                    **_errors("400", "401", "403", "404", "500"),
                },
            }
        },
        "/api/v1/services/{service}/properties/{path}/stream": {
            "get": {
                "summary": "A live image: every value of a binary property as multipart/x-mixed-replace",
                "description": (
                    "One part per value (MJPEG for image/jpeg), each with `Content-Type` (the"
                    " property's media type), `Content-Length`, `X-Sequence` and `X-Conflated`; a slow"
                    " reader gets the latest value only. The body ends with the closing boundary when"
                    " the property goes away. Bounded like the event streams (`http.max_streams`,"
                    " `http.max_streams_per_client`, `http.write_timeout`)."
                ),
                "parameters": [
                    _SERVICE,
                    _PATH,
                    {
                        "name": "parameters",
                        "in": "query",
                        "description": "Request parameters of the Listen.",
                        "schema": {"type": "object", "additionalProperties": {"type": "string"}},
                        "style": "form",
                        "explode": True,
                    },
                ],
                "responses": {
                    "200": {
                        "description": "The parts, boundary `psframe`",
                        "content": {"multipart/x-mixed-replace": {"schema": _BINARY}},
                    },
                    **_errors("400", "401", "403", "404", "429", "503", "504"),
                },
            }
        },
        "/api/v1/events": {
            "get": {
                "summary": "Listen as Server-Sent Events",
                "description": (
                    "`event: value` messages (`id:` the stream's sequence, `data:` an Event) carry the"
                    " current value of every match, then `event: sync` (`data: {}`), then changes;"
                    " `: heartbeat` comments when idle; `event: error` (`data: {code, message}`) ends a"
                    " failed stream. With `Last-Event-ID` the snapshot's values carry `gap: true`."
                ),
                "parameters": [
                    {
                        "name": "sel",
                        "in": "query",
                        "required": True,
                        "description": "SERVICE/PATH; `*` may stand for the service or a path segment.",
                        "schema": {"type": "array", "items": {"type": "string"}},
                        "style": "form",
                        "explode": True,
                    },
                    {
                        "name": "Last-Event-ID",
                        "in": "header",
                        "required": False,
                        "description": "Sent by EventSource when it reconnects.",
                        "schema": {"type": "string"},
                    },
                ],
                "responses": {
                    "200": {
                        "description": "The event stream",
                        "content": {"text/event-stream": {"schema": {"$ref": "#/components/schemas/Event"}}},
                    },
                    **_errors("400", "401", "403", "429", "503"),
                },
            }
        },
        "/api/v1/openapi.json": {
            "get": {
                "summary": "This document",
                "responses": {"200": _json({"type": "object"}, "OpenAPI 3.1")},
            }
        },
        "/api/v1/health": {
            "get": {
                "summary": "Whether the front end answers",
                "responses": {
                    "200": _json({"type": "object", "properties": {"status": {"const": "ok"}}}, "It answers")
                },
            }
        },
        "/": {
            "get": {
                "summary": "The browser console (index.html)",
                "responses": {"200": {"description": "HTML", "content": {"text/html": {}}}, "404": _ERROR},
            }
        },
        "/console/floor-plan.json": {
            "get": {
                "summary": "The console's floor plan ([console] map_image): its route and where it lies",
                "responses": {
                    "200": _json(
                        {
                            "type": "object",
                            "properties": {
                                "image": {"type": ["string", "null"]},
                                "extent": {
                                    "type": ["array", "null"],
                                    "items": {"type": "number"},
                                    "minItems": 4,
                                    "maxItems": 4,
                                },
                            },
                        },
                        "The route of the picture (null: none) and [x0, y0, x1, y1] in metres",
                    )
                },
            }
        },
        "/console/floor-plan": {
            "get": {
                "summary": "The console's floor-plan picture",
                "responses": {"200": {"description": "The picture"}, "404": _ERROR},
            }
        },
        "/console/{file}": {
            "get": {
                "summary": "A file of the browser console",
                "parameters": [
                    {"name": "file", "in": "path", "required": True, "schema": {"type": "string"}}
                ],
                "responses": {"200": {"description": "The file"}, "404": _ERROR},
            }
        },
    },
    "components": {
        "responses": {
            "Error": _json({"$ref": "#/components/schemas/Error"}, "An error, with the gRPC code name"),
        },
        "schemas": {
            "Error": {
                "type": "object",
                "required": ["error"],
                "properties": {
                    "error": {
                        "type": "object",
                        "required": ["code", "message"],
                        "properties": {"code": {"type": "string"}, "message": {"type": "string"}},
                    }
                },
            },
            "Value": {
                "type": "object",
                "description": "`value` for text; `data` and `media_type` for a binary value.",
                "required": ["service", "path"],
                "properties": {
                    "service": {"type": "string"},
                    "path": {"type": "string"},
                    "value": {"type": "string"},
                    "data": _BASE64,
                    "media_type": {"type": "string"},
                    "time": {
                        "type": "number",
                        "description": "The value's source time, seconds since the epoch.",
                    },
                },
            },
            "History": {
                "type": "object",
                "required": ["service", "path", "events", "truncated"],
                "properties": {
                    "service": {"type": "string"},
                    "path": {"type": "string"},
                    "events": {"type": "array", "items": {"$ref": "#/components/schemas/Event"}},
                    "truncated": {"type": "boolean"},
                },
            },
            "Snapshot": {
                "type": "object",
                "required": ["service", "path", "values"],
                "properties": {
                    "service": {"type": "string"},
                    "path": {"type": "string"},
                    "values": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "properties": {
                                "path": {"type": "string"},
                                "value": {"type": "string"},
                                "data": _BASE64,
                                "media_type": {"type": "string"},
                                "time": {"type": "number"},
                            },
                        },
                    },
                },
            },
            "Services": {
                "type": "object",
                "properties": {
                    "services": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "properties": {
                                "name": {"type": "string"},
                                "type": {"type": "string"},
                                "state": {"enum": ["up", "down", "connecting", "unknown"]},
                                "address": {"type": "string"},
                                "location": {"type": ["array", "null"], "items": {"type": "number"}},
                            },
                        },
                    },
                    "next": {
                        "type": ["string", "null"],
                        "description": "The page's last name: the next page's `after` (null: no more)",
                    },
                },
            },
            "Parameter": {
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "type": {"type": "string"},
                    "required": {"type": "boolean"},
                    "default": _NULLABLE_TEXT,
                    "doc": _NULLABLE_TEXT,
                },
            },
            "Model": {
                "type": "object",
                "properties": {
                    "service": {"type": "string"},
                    "type": {"type": "string"},
                    "doc": _NULLABLE_TEXT,
                    "properties": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "properties": {
                                "name": {"type": "string"},
                                "type": {"type": "string"},
                                "access": {
                                    "enum": ["read", "write", "read-write", "action", "query", "unknown"]
                                },
                                "unit": _NULLABLE_TEXT,
                                "minimum": {"type": ["number", "null"]},
                                "maximum": {"type": ["number", "null"]},
                                "choices": {"type": ["array", "null"], "items": {"type": "string"}},
                                "length": {"type": ["integer", "null"]},
                                "gui": _NULLABLE_TEXT,
                                "doc": _NULLABLE_TEXT,
                                "media_type": _NULLABLE_TEXT,
                                "max_size": {"type": ["integer", "null"]},
                                "resolution": {"type": ["number", "null"]},
                                "value": {
                                    "oneOf": [{"$ref": "#/components/schemas/Parameter"}, {"type": "null"}]
                                },
                                "parameters": {
                                    "type": "array",
                                    "items": {"$ref": "#/components/schemas/Parameter"},
                                },
                            },
                        },
                    },
                },
            },
            "Event": {
                "type": "object",
                "properties": {
                    "service": {"type": "string"},
                    "path": {"type": "string"},
                    "value": {"type": "string"},
                    "data": _BASE64,
                    "media_type": {"type": "string"},
                    "gap": {"type": "boolean"},
                    "removed": {"type": "boolean"},
                    "conflated": {"type": "integer"},
                    "sequence": {
                        "type": "integer",
                        "description": "In a history: the property's count of kept changes.",
                    },
                    "time": {"type": "number"},
                },
            },
        },
    },
}


def document(console: bool) -> dict[str, Any]:
    """The document; without the console its two routes are left out."""
    if console:
        return DOCUMENT
    paths = {p: v for p, v in DOCUMENT["paths"].items() if not (p == "/" or p.startswith("/console/"))}
    return {**DOCUMENT, "paths": paths}
