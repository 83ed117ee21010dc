"""services.kernel.sharing: one upstream listen per (path, parameters), shared and reference counted."""

from __future__ import annotations

import asyncio

import pytest

from services.kernel.backend import Change
from services.kernel.errors import NotFound
from services.kernel.sharing import SharedListen, SharedListens, listen_key


class Upstream:
    """Records what the table opens and closes; ``refuse`` makes the next open fail."""

    def __init__(self) -> None:
        self.opened: list[tuple[str, dict[str, str]]] = []
        self.closed: list[tuple[str, dict[str, str]]] = []
        self.gate: asyncio.Event | None = None
        self.refuse = False

    async def open(self, entry: SharedListen) -> None:
        self.opened.append((entry.path, entry.params))
        if self.gate is not None:
            await self.gate.wait()
        if self.refuse:
            raise NotFound(f"no {entry.path}")

    async def close(self, entry: SharedListen) -> None:
        self.closed.append((entry.path, entry.params))

    def table(self) -> SharedListens[SharedListen]:
        return SharedListens(SharedListen, self.open, self.close)


def test_the_key_is_the_path_and_the_parameters_in_any_order() -> None:
    assert listen_key("location", {"frame": "map", "unit": "m"}) == listen_key(
        "location", {"unit": "m", "frame": "map"}
    )
    assert listen_key("location", {}) != listen_key("location", {"frame": "map"})


async def test_one_upstream_per_key_closed_when_the_last_listener_leaves() -> None:
    upstream = Upstream()
    table = upstream.table()
    heard: list[Change] = []
    first = await table.listen("x", heard.append, {})
    second = await table.listen("x", heard.append, {})
    framed = await table.listen("x", heard.append, {"frame": "map"})
    assert upstream.opened == [("x", {}), ("x", {"frame": "map"})]
    assert len(table) == 2 and len(table.on_path("x")) == 2
    for entry in table.on_path("x"):
        entry.deliver(Change("x", "1"))
    assert len(heard) == 3
    await first.close()
    assert upstream.closed == []
    await second.close()
    await second.close()  # a second close is harmless
    assert upstream.closed == [("x", {})]
    assert table.paths() == ["x"]
    await framed.close()
    assert upstream.closed == [("x", {}), ("x", {"frame": "map"})]
    assert len(table) == 0 and table.on_path("x") == []


async def test_listeners_arriving_while_it_opens_wait_and_share_its_failure() -> None:
    upstream = Upstream()
    upstream.gate = asyncio.Event()
    upstream.refuse = True
    table = upstream.table()
    waiting = [asyncio.create_task(table.listen("gone", print, {})) for _ in range(3)]
    await asyncio.sleep(0)
    upstream.gate.set()
    results = await asyncio.gather(*waiting, return_exceptions=True)
    assert all(isinstance(r, NotFound) for r in results)
    assert upstream.opened == [("gone", {})] and len(table) == 0
    upstream.refuse = False
    await table.listen("gone", print, {})
    assert len(table) == 1


async def test_a_dropped_entry_is_still_closed_by_its_last_listener_and_a_new_one_opens() -> None:
    upstream = Upstream()
    table = upstream.table()
    sub = await table.listen("tool.level", print, {})
    (entry,) = table.on_path("tool.level")
    assert table.drop(entry) and not table.drop(entry) and not table.holds(entry)
    await table.listen("tool.level", print, {})
    assert len(upstream.opened) == 2
    await sub.close()
    assert upstream.closed == [("tool.level", {})]
    assert len(table) == 1


async def test_a_listener_that_raises_does_not_stop_the_others(caplog: pytest.LogCaptureFixture) -> None:
    table = Upstream().table()
    heard: list[str] = []

    def broken(change: Change) -> None:
        raise RuntimeError("listener bug")

    await table.listen("x", broken, {})
    await table.listen("x", lambda c: heard.append(c.value), {})
    (entry,) = table
    entry.deliver(Change("x", "7"))
    assert heard == ["7"]
    assert "a listener of x failed" in caplog.text


async def test_clear_empties_the_table_for_its_owner_to_close() -> None:
    table = Upstream().table()
    await table.listen("a", print, {})
    await table.listen("b", print, {"p": "1"})
    entries = table.clear()
    assert [(e.path, e.params) for e in entries] == [("a", {}), ("b", {"p": "1"})]
    assert len(table) == 0 and table.on_path("a") == []
