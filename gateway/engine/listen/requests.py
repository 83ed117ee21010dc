"""A Listen request checked against the limits: its selectors and its options."""

from __future__ import annotations

import functools
import math

from gateway.config import Limits
from gateway.engine.events import ListenRequest, Selector, StreamOptions
from gateway.engine.router import check_pattern
from services.kernel.errors import InvalidArgument, ResourceExhausted
from services.kernel.paths import WILDCARD, validate_service_name

#: Checked selectors and options are immutable, so a Listen is handed the same objects as every
#: Listen that asked alike: a gateway holding thousands of Listens of a few properties keeps one
#: of each (about 300 bytes a Listen less). Bounded: beyond this many, least recently used first.
SHARED_PARSES = 4096


@functools.lru_cache(maxsize=SHARED_PARSES)
def _shared_selector(service: str, path: str, params: tuple[tuple[str, str], ...]) -> Selector:
    return Selector(service, path, params)


@functools.lru_cache(maxsize=SHARED_PARSES)
def _shared_options(
    updates_only: bool, min_interval: float, sample_interval: float, heartbeat_interval: float, max_batch: int
) -> StreamOptions:
    return StreamOptions(updates_only, min_interval, sample_interval, heartbeat_interval, max_batch)


def _seconds(s: float, name: str, floor: float) -> float:
    if s < 0:
        raise InvalidArgument(f"options.{name} must not be negative")
    if not math.isfinite(s):
        raise InvalidArgument(f"options.{name} must be a finite number of seconds")
    if 0 < s < floor:
        raise InvalidArgument(f"options.{name} of {s * 1000:g} ms is below the floor of {floor * 1000:g} ms")
    return s


def check_listen(request: ListenRequest, limits: Limits) -> tuple[list[Selector], StreamOptions]:
    """The request's selectors (each once) and options, checked against the limits; raises
    InvalidArgument or ResourceExhausted."""
    return _selectors(request, limits), _options(request, limits)


def _options(request: ListenRequest, limits: Limits) -> StreamOptions:
    floor = limits.min_interval_floor
    max_batch = limits.max_batch if request.max_batch <= 0 else min(request.max_batch, limits.max_batch)
    return _shared_options(
        request.updates_only,
        _seconds(request.min_interval, "min_interval", floor),
        _seconds(request.sample_interval, "sample_interval", floor),
        _seconds(request.heartbeat_interval, "heartbeat_interval", floor),
        max_batch,
    )


def _checked(selector: Selector) -> Selector:
    service = selector.service
    if not service:
        raise InvalidArgument("a Listen selector needs a service (or * for every service)")
    if service != WILDCARD:
        validate_service_name(service)
    check_pattern(selector.path)
    return _shared_selector(service, selector.path, tuple(sorted(selector.params)))


def _selectors(request: ListenRequest, limits: Limits) -> list[Selector]:
    count = len(request.selectors)
    if count > limits.max_selectors:
        raise ResourceExhausted(
            f"a Listen may have at most {limits.max_selectors} selectors, this one has {count}"
        )
    if not count:
        raise InvalidArgument("a Listen needs at least one selector")
    # The same selector twice would only double the bookkeeping.
    return list(dict.fromkeys(_checked(sel) for sel in request.selectors))
