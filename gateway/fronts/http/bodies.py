"""What an HTTP request carries, checked: a Set's body, request parameters, and JSON values.

A Set's body is ``{"value": TEXT, "parameters": {"name": "text"}}``, or for a binary property
``{"data": BASE64, "parameters": {...}}`` (or the raw bytes, :mod:`gateway.fronts.http.api`).
Values travel as text (the value grammar of ``services.kernel.values``); for convenience a JSON
number, boolean or array is formatted into that grammar here (``1.5`` → ``1.5``, ``true`` →
``true``, ``[1, 2]`` → ``(1 2)``), so that ``{"value": 0.5}`` and ``{"value": "0.5"}`` are the
same Set. Anything that does not fit is INVALID_ARGUMENT naming what is wrong.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from aiohttp import web
from multidict import MultiMapping

from gateway.fronts.http.binary import decode_data
from services.kernel.errors import InvalidArgument, ResourceExhausted
from services.kernel.values import format_bool, format_list, format_number

_SET_KEYS = ("value", "data", "parameters")
_EXAMPLE = '{"value": "(1 0 0)", "parameters": {"frame": "robot"}}'
#: Bytes of a request body read at a time.
_CHUNK = 64 * 1024


class BodyTooLarge(ResourceExhausted):
    """A request body over its bound: RESOURCE_EXHAUSTED, answered 413 (the request is too large)."""


@dataclass(frozen=True, slots=True)
class SetBody:
    """A Set's body: the value (text, or bytes for a binary property) and the request parameters."""

    value: str | bytes
    parameters: Mapping[str, str]


async def read_body(request: web.Request, limit: int, bound: str) -> bytes:
    """The whole body of ``request``, at most ``limit`` bytes; BodyTooLarge naming ``bound`` beyond
    (at once when Content-Length announces more, else as soon as more has come)."""
    length = request.content_length
    if length is not None and length > limit:
        raise BodyTooLarge(f"the request body is {length} bytes, more than {bound} ({limit} bytes)")
    chunks = []
    size = 0
    async for chunk in request.content.iter_chunked(_CHUNK):
        size += len(chunk)
        if size > limit:
            raise BodyTooLarge(f"the request body is more than {bound} ({limit} bytes)")
        chunks.append(chunk)
    return b"".join(chunks)


def value_text(value: Any, where: str) -> str:
    """A JSON value as value text; InvalidArgument for null and objects."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return format_bool(value)
    if isinstance(value, int | float):
        return format_number(value)
    if isinstance(value, list):
        return format_list(value)
    kind = "null" if value is None else "an object"
    raise InvalidArgument(f"{where} must be a string, a number, a boolean or an array, not {kind}")


def _refuse_constant(name: str) -> float:
    # json.loads accepts NaN and Infinity, which are not JSON and not values of the grammar.
    raise InvalidArgument(f"the body is not valid JSON: {name} is not a JSON number")


def parse_set_body(body: bytes) -> SetBody:
    """The Set request in ``body`` (JSON); InvalidArgument naming what is wrong."""
    try:
        data = json.loads(body, parse_constant=_refuse_constant)
    except UnicodeDecodeError as exc:
        raise InvalidArgument(f"the body is not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    except ValueError as exc:
        raise InvalidArgument(f"the body is not valid JSON: {exc}; expected {_EXAMPLE}") from None
    except RecursionError:
        raise InvalidArgument("the body is not valid JSON: it nests too deeply") from None
    if not isinstance(data, dict):
        raise InvalidArgument(f"the body must be a JSON object like {_EXAMPLE}")
    unknown = [key for key in data if key not in _SET_KEYS]
    if unknown:
        raise InvalidArgument(f"the body has an unknown key {unknown[0]!r} (known: value, data, parameters)")
    if "value" in data and "data" in data:
        raise InvalidArgument("the body has both 'value' (text) and 'data' (base64 bytes): send one")
    value: str | bytes
    if "data" in data:
        value = decode_data(data["data"])
    elif "value" in data:
        value = value_text(data["value"], "'value'")
    else:
        raise InvalidArgument(f"the body needs a 'value', like {_EXAMPLE} (or 'data', base64, for bytes)")
    raw = data.get("parameters", {})
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise InvalidArgument("'parameters' must be a JSON object of names to values")
    parameters = {str(name): value_text(v, f"parameter {name!r}") for name, v in raw.items()}
    return SetBody(value, parameters)


def query_parameters(query: MultiMapping[str], ignore: tuple[str, ...] = ()) -> dict[str, str]:
    """The request parameters in a query string (``?frame=robot``); a name given twice is refused."""
    parameters: dict[str, str] = {}
    for name, value in query.items():
        if name in ignore:
            continue
        if name in parameters:
            raise InvalidArgument(f"request parameter {name!r} is given more than once")
        parameters[name] = value
    return parameters
