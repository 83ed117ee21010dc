"""The scheduler's records: providers as it sees them, requests, plans, allocations, waiting requests."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

from services.kernel.values import Vector

__all__ = ["Allocation", "Plan", "Provider", "ProviderState", "Request", "Waiting"]


class ProviderState(enum.Enum):
    """A provider's availability as the scheduler needs it (from the registry entry's state)."""

    READY = "ready"  # up and free: may be chosen
    DORMANT = "dormant"  # declared, not running: woken only when the ready ones cannot serve
    BUSY = "busy"  # serving someone (active, or held by a licence taken outside the scheduler)
    DOWN = "down"  # down, dead or not reached yet: never chosen


@dataclass(frozen=True, slots=True)
class Provider:
    """One service that may provide: its capabilities (type and features), state and location."""

    name: str
    capabilities: frozenset[str]
    state: ProviderState
    location: Vector | None = None
    #: A cost the provider published itself (the request's ``cost`` option names the property).
    cost: float | None = None


@dataclass(frozen=True, slots=True)
class Request:
    """What a consumer asks for.

    ``count`` 1 covers ``capabilities`` with as few providers as possible (composition);
    ``count`` k > 1 asks for k providers that each offer all of them (a team of helpers).
    """

    consumer: str
    capabilities: frozenset[str]
    count: int = 1
    location: Vector | None = None
    duration: float = 60.0
    wait: float = 0.0
    exclude: frozenset[str] = frozenset()
    weight: float = 0.5
    #: The cost that scores 1 (the largest of every provider that could serve); None: the largest
    #: among those offered to the scheduler.
    cost_scale: float | None = None


@dataclass(frozen=True, slots=True)
class Plan:
    """Providers chosen for a request and reserved, before their licences are granted."""

    id: str
    request: Request
    providers: tuple[str, ...]
    #: The dormant ones among them: woken before their licences are granted.
    wake: tuple[str, ...]
    #: Each chosen provider's cost and score (lower is better), for the answer and the log.
    costs: dict[str, float] = field(default_factory=dict)


@dataclass(slots=True)
class Allocation:
    """Providers held by one consumer under licences until ``expires_at``."""

    id: str
    consumer: str
    capabilities: frozenset[str]
    licences: dict[str, str]  # provider -> licence id
    granted_at: float
    expires_at: float
    #: Who the licences were granted to (the caller that asked; releases are its alone).
    holder: str = ""
    #: "active", then "released", "expired" or "lost" (every licence ended otherwise than by release).
    status: str = "active"
    #: Providers whose licence ended before the allocation did, and how (expired, lost, released).
    ended: dict[str, str] = field(default_factory=dict)

    @property
    def providers(self) -> tuple[str, ...]:
        return tuple(self.licences)

    def live(self) -> list[str]:
        """The providers still held."""
        return [p for p in self.licences if p not in self.ended] if self.status == "active" else []


@dataclass(frozen=True, slots=True)
class Waiting:
    """A request queued because every provider that could serve it is busy."""

    id: str
    request: Request
    since: float
    deadline: float
