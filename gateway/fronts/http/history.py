"""``GET /api/v1/services/{service}/properties/{path}/history``: the History call as JSON.

``since`` and ``until`` are each a time: seconds since the epoch (``1767225600.5``, as an
event's ``time``), ISO-8601 (``2026-01-01T00:00:00Z``; without a zone, UTC), or a duration
before now (``90s``, ``5m``, ``2h``, ``1d``, ``250ms``); unset is open. ``limit`` is the most
events answered (0 or unset: the gateway's ``[history] default_limit``). The answer is
``{"service", "path", "events": [Event…], "truncated"}``, each event as the event stream's
``data`` (with its ``sequence``), oldest first.
"""

from __future__ import annotations

import math
import re
import time
from datetime import UTC, datetime

from aiohttp import web

from gateway.engine.guard import Guard
from gateway.engine.history import HistoryKeeper, HistoryQuery, kept_history
from gateway.fronts.http.api import json_response
from gateway.fronts.http.binary import MediaTypes
from gateway.fronts.http.events import event_json
from gateway.fronts.http.safety import identify
from services.kernel.errors import InvalidArgument

#: A duration before now: a number and its unit.
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(ms|s|m|h|d)\s*$")
_UNIT_NS = {
    "ms": 1_000_000,
    "s": 1_000_000_000,
    "m": 60_000_000_000,
    "h": 3_600_000_000_000,
    "d": 86_400_000_000_000,
}
#: The query keys taken; any other is refused (a typo must not pass unnoticed).
_KEYS = frozenset({"since", "until", "limit"})


def parse_time(text: str, now_ns: int, name: str) -> int:
    """``text`` as ns since the epoch (see the module docstring); InvalidArgument naming ``name``."""
    found = _DURATION.match(text)
    if found is not None:
        return now_ns - int(float(found.group(1)) * _UNIT_NS[found.group(2)])
    try:
        seconds = float(text)
    except ValueError:
        pass
    else:
        if not math.isfinite(seconds) or seconds < 0:
            raise InvalidArgument(f"{name} must be a time after 1970, got {text[:50]!r}")
        return int(seconds * 1e9)
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise InvalidArgument(
            f"{name} must be seconds since the epoch, an ISO-8601 time or a duration before now"
            f" like 60s or 5m, got {text[:50]!r}"
        ) from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return int(when.timestamp() * 1_000_000) * 1000


class HistoryRoute:
    """The history route's handler: the same keeper, rules and limits as the gRPC History call."""

    def __init__(self, history: HistoryKeeper | None, guard: Guard, media_types: MediaTypes) -> None:
        self.history = history
        self.guard = guard
        self.media_types = media_types

    async def history_json(self, request: web.Request) -> web.Response:
        service = request.match_info["service"]
        path = request.match_info["path"]
        query = request.query
        unknown = sorted(set(query) - _KEYS)
        if unknown:
            raise InvalidArgument(f"unknown query key {unknown[0][:50]!r} (known: since, until, limit)")
        now = time.time_ns()
        since = parse_time(query["since"], now, "since") if "since" in query else None
        until = parse_time(query["until"], now, "until") if "until" in query else None
        limit_text = query.get("limit", "0")
        if not limit_text.isdigit() or len(limit_text) > 9:
            raise InvalidArgument(f"limit must be a whole number, got {limit_text[:50]!r}")
        subject = identify(request, self.guard)
        reply = kept_history(
            self.history, HistoryQuery(service, path, since, until, int(limit_text)), subject
        )
        events = []
        for event in reply.events:
            media_type = (
                await self.media_types.of(event.service, event.path) if isinstance(event.value, bytes) else ""
            )
            item = event_json(event, False, media_type)
            item["sequence"] = event.sequence
            events.append(item)
        return json_response(
            {"service": service, "path": path, "events": events, "truncated": reply.truncated}
        )
