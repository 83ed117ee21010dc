"""Keys written in the background: the newest value of each key, the puts of one folder in one bulk write."""

from __future__ import annotations

import json

from support.memory_store import MemoryServer

from gateway.cluster.writer import LatestWrites
from services.apps.registry.store import Kind


async def test_waiting_puts_of_one_folder_go_in_one_bulk_write_the_newest_value_each() -> None:
    server = MemoryServer()
    store = server.store("gw-a")
    await store.start()
    server.write(Kind.STATE, "gone", "up", "gw-a")
    writes = LatestWrites(store)
    names = [f"dev{n:03d}" for n in range(300)]
    for name in names:
        writes.put(Kind.STATE, name, "connecting")
    writes.put(Kind.GATEWAY, "gw-a", json.dumps({"address": "127.0.0.1:1", "owned": 300}))
    for name in names:
        writes.put(Kind.STATE, name, "up")  # replaces the waiting value, keeps its place
    writes.put(Kind.STATE, "gone", None)
    await writes.flush()
    assert store.bulk_calls == [("put_many", Kind.STATE, 300), ("put_many", Kind.GATEWAY, 1)]
    assert ("delete", Kind.STATE, "gone") in store.writes
    assert server.folder(Kind.STATE) == dict.fromkeys(names, "up")
    server.end_lease("gw-a")  # leased, as a state is
    assert server.folder(Kind.STATE) == {}
    await writes.aclose()


async def test_a_write_the_store_refuses_is_dropped_and_the_next_ones_go() -> None:
    server = MemoryServer()
    store = server.store("gw-a")
    await store.start()
    writes = LatestWrites(store)
    server.stop()
    writes.put(Kind.STATE, "bot", "up")
    await writes.flush()  # refused: dropped with a log line, nothing raised
    assert server.folder(Kind.STATE) == {}
    server.start()
    writes.put(Kind.STATE, "bot", "down")
    await writes.flush()
    assert server.folder(Kind.STATE) == {"bot": "down"}
    await writes.aclose()
