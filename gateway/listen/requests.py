"""A Listen request, parsed: its selectors and its options, checked against the limits."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass

from google.protobuf.duration_pb2 import Duration

from gateway.config import Limits
from gateway.router import check_pattern
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.errors import InvalidArgument, ResourceExhausted
from services.paths import WILDCARD, validate_service_name


@dataclass(frozen=True, slots=True)
class Selector:
    """What a Listen asks for: a service (or ``*``), a path (``*`` segments allowed), parameters."""

    service: str
    path: str
    params: tuple[tuple[str, str], ...] = ()

    def matches_service(self, name: str) -> bool:
        return self.service in (WILDCARD, name)


@dataclass(frozen=True, slots=True)
class StreamOptions:
    """Parsed ``ListenOptions``; intervals in seconds, 0 = off."""

    updates_only: bool = False
    min_interval: float = 0.0
    sample_interval: float = 0.0
    heartbeat_interval: float = 0.0
    max_batch: int = 256


#: Parsed selectors and options are immutable, so a Listen is handed the same objects as every
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


def _seconds(d: Duration, name: str, floor: float) -> float:
    if d.seconds < 0 or d.nanos < 0:
        raise InvalidArgument(f"options.{name} must not be negative")
    s = d.seconds + d.nanos / 1e9
    if 0 < s < floor:
        raise InvalidArgument(f"options.{name} of {s * 1000:g} ms is below the floor of {floor * 1000:g} ms")
    return s


def parse_options(opts: pb.ListenOptions, limits: Limits) -> StreamOptions:
    """Check ``ListenOptions`` against the limits; raises InvalidArgument."""
    floor = limits.min_interval_floor
    max_batch = limits.max_batch if opts.max_batch == 0 else min(opts.max_batch, limits.max_batch)
    return _shared_options(
        opts.updates_only,
        _seconds(opts.min_interval, "min_interval", floor),
        _seconds(opts.sample_interval, "sample_interval", floor),
        _seconds(opts.heartbeat_interval, "heartbeat_interval", floor),
        max_batch,
    )


def _selector(service: str, path: str, params: Mapping[str, str], default_service: str) -> Selector:
    service = service or default_service
    if not service:
        raise InvalidArgument("a Listen selector needs a service (or * for every service)")
    if service != WILDCARD:
        validate_service_name(service)
    check_pattern(path)
    return _shared_selector(service, path, tuple(sorted(params.items())))


def parse_selectors(request: pb.ListenRequest, limits: Limits) -> list[Selector]:
    """The request's selectors (its own and ``more``; an empty service in ``more`` = the request's)."""
    count = 1 + len(request.more)
    if count > limits.max_selectors:
        raise ResourceExhausted(
            f"a Listen may have at most {limits.max_selectors} selectors, this one has {count}"
        )
    selectors = [_selector(request.service, request.property, request.parameters, "")]
    for ref in request.more:
        selectors.append(_selector(ref.service, ref.property, ref.parameters, request.service))
    # The same selector twice would only double the bookkeeping.
    return list(dict.fromkeys(selectors))
