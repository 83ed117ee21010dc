"""The history keeper's rings, bounds and answers, in-process on a fake clock.

Changes are handed to the keeper as its listen streams hand them (``keep``); what a caller gets
back is what :meth:`HistoryKeeper.query` answers. Values older than the rings come from an
"older events" source with the recorder's signature (a fake one here).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from gateway.config import HistorySection, Limits
from gateway.engine.events import Event
from gateway.engine.guard import Guard
from gateway.engine.history import ENTRY_OVERHEAD_BYTES, HistoryKeeper, HistoryQuery
from gateway.engine.identity import ANONYMOUS
from gateway.engine.listen import ListenHub
from gateway.engine.router import Router
from gateway.engine.rules import Rule, Rules, Subject
from services.kernel.errors import InvalidArgument, NotFound

S = 1_000_000_000


def keeper(**settings: object) -> HistoryKeeper:
    options = {"selectors": ("*/x",), **settings}
    section = HistorySection(**options)  # type: ignore[arg-type]
    guard = Guard()
    return HistoryKeeper(ListenHub(Router(guard), Limits(), 1.0), section, guard, clock=lambda: 100 * S)


def change(service: str, path: str, value: str | bytes, t: int) -> Event:
    return Event(service, path, value, 0, t * S)


def values(k: HistoryKeeper, service: str = "*", path: str = "x", **query: int) -> list[tuple[str, object]]:
    reply = k.query(HistoryQuery(service, path, **query), ANONYMOUS)  # type: ignore[arg-type]
    return [(e.service, e.value) for e in reply.events]


def test_each_property_keeps_its_latest_changes_numbered() -> None:
    k = keeper(size=3)
    for t in range(5):
        k.keep(change("a", "x", str(t), t))
    reply = k.query(HistoryQuery("a", "x"), ANONYMOUS)
    assert [(e.value, e.sequence, e.time_ns) for e in reply.events] == [
        ("2", 3, 2 * S),
        ("3", 4, 3 * S),
        ("4", 5, 4 * S),
    ]
    assert k.kept_entries == 3


def test_past_the_total_bound_the_oldest_change_of_all_goes_first() -> None:
    k = keeper(size=10, max_entries=4)
    k.keep(change("a", "x", "a0", 0))
    k.keep(change("b", "x", "b1", 1))
    k.keep(change("a", "x", "a2", 2))
    k.keep(change("b", "x", "b3", 3))
    k.keep(change("c", "x", "c4", 4))
    assert values(k) == [("b", "b1"), ("a", "a2"), ("b", "b3"), ("c", "c4")]
    k.keep(change("c", "x", "c5", 5))
    k.keep(change("c", "x", "c6", 6))
    assert values(k) == [("b", "b3"), ("c", "c4"), ("c", "c5"), ("c", "c6")]
    assert k.kept_entries == 4
    assert set(k.rings) == {("b", "x"), ("c", "x")}, "a ring left empty goes"


def test_the_bytes_bound_counts_values_and_entries() -> None:
    k = keeper(size=100, max_bytes=3 * (1000 + ENTRY_OVERHEAD_BYTES))
    for t in range(10):
        k.keep(change("a", "x", "v" * 1000, t))
    assert k.kept_entries == 3
    assert k.kept_bytes <= 3 * (1000 + ENTRY_OVERHEAD_BYTES)


def test_binary_values_are_kept_only_when_asked() -> None:
    off = keeper()
    off.keep(change("cam", "x", b"\xff\xd8", 1))
    off.keep(change("cam", "x", "text", 2))
    assert values(off) == [("cam", "text")]
    assert off.skipped_binary == 1
    on = keeper(binary=True)
    on.keep(change("cam", "x", b"\xff\xd8", 1))
    assert values(on) == [("cam", b"\xff\xd8")]


def test_since_until_and_limit() -> None:
    k = keeper(default_limit=3, max_limit=5)
    for t in range(10):
        k.keep(change("a", "x", str(t), t))
    assert values(k, since_ns=4 * S, until_ns=6 * S) == [("a", "4"), ("a", "5")]
    reply = k.query(HistoryQuery("a", "x"), ANONYMOUS)
    assert [e.value for e in reply.events] == ["0", "1", "2"] and reply.truncated
    reply = k.query(HistoryQuery("a", "x", limit=100), ANONYMOUS)
    assert len(reply.events) == 5 and reply.truncated, "bounded by max_limit whatever is asked"
    with pytest.raises(InvalidArgument, match="until is before since"):
        k.query(HistoryQuery("a", "x", since_ns=5 * S, until_ns=4 * S), ANONYMOUS)


def test_a_property_outside_the_selectors_is_not_found_and_a_followed_one_may_be_empty() -> None:
    k = keeper()
    with pytest.raises(NotFound):
        k.query(HistoryQuery("a", "y"), ANONYMOUS)
    assert k.query(HistoryQuery("a", "x"), ANONYMOUS).events == []


@dataclass(frozen=True)
class Recorded:
    """What the recorder's reading hands back (services.apps.recorder.reading.RecordedEvent)."""

    service: str
    path: str
    value: str | bytes
    time_ns: int
    log_time_ns: int
    sequence: int
    conflated: int = 0
    gap: bool = False
    removed: bool = False


class FakeRecordings:
    """An older-events source with the recorder's signature (``until_ns`` included, as the
    recorder's reader has it), over a list of recorded changes."""

    def __init__(self, recorded: list[Recorded]) -> None:
        self.recorded = recorded
        self.asked: list[tuple[object, ...]] = []

    def __call__(
        self,
        directory: Path,
        service_glob: str,
        path_glob: str,
        *,
        since_ns: int | None,
        until_ns: int | None,
        limit: int,
    ) -> list[Recorded]:
        self.asked.append((directory, service_glob, path_glob, since_ns, until_ns, limit))
        found = [
            r
            for r in self.recorded
            if (since_ns is None or r.time_ns >= since_ns) and (until_ns is None or r.time_ns <= until_ns)
        ]
        return found[:limit]


def test_values_older_than_the_rings_come_from_the_recordings() -> None:
    recordings = FakeRecordings(
        [Recorded("a", "x", str(t), t * S, t * S, t + 1) for t in range(6)]
        + [Recorded("secret", "x", "hidden", 3 * S, 3 * S, 1)]
    )
    rules = Rules((Rule.build(0, subject="*", service="a", operations=("read",), effect="permit"),))
    k = HistoryKeeper(
        ListenHub(Router(Guard(rules)), Limits(), 1.0),
        HistorySection(selectors=("*/x",), size=3, recordings="/recordings"),
        Guard(rules),
        older=recordings,
        clock=lambda: 100 * S,
    )
    for t in range(6):  # the ring keeps 3..5 of them: complete from 3 s on
        k.keep(change("a", "x", str(t), t))
    caller = Subject("someone", authenticated=True)
    reply = k.query(HistoryQuery("*", "x", since_ns=1 * S), caller)
    assert [(e.service, e.value) for e in reply.events] == [
        ("a", "1"),
        ("a", "2"),
        ("a", "3"),
        ("a", "4"),
        ("a", "5"),
    ]
    # Up to the rings' start, which the recordings' reader includes: the nanosecond before it.
    assert recordings.asked == [(Path("/recordings"), "*", "x", 1 * S, 3 * S - 1, 1001)]
    # Within the rings, the recordings are not asked.
    recordings.asked.clear()
    assert [e.value for e in k.query(HistoryQuery("a", "x", since_ns=4 * S), caller).events] == ["4", "5"]
    assert recordings.asked == []
