"""The embedded registry store, and the registry keeping its registrations through a store: the
``store`` property, and registrations refused while the store is read-only."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from support.group_support import MemoryDirectory, sim_robot
from support.ports import free_port

from gateway.stores import EtcdStore, parse_store_url
from services.apps.registry import Registry, RegistryService
from services.apps.registry.embedded import EmbeddedStore
from services.apps.registry.store import EMBEDDED, RegistryStore, decode_registration, encode_registration
from services.kernel.errors import Code, InvalidArgument, PropertyError


@pytest.fixture
async def world() -> AsyncIterator[MemoryDirectory]:
    directory = MemoryDirectory()
    directory.devices["tcp://127.0.0.1:7001"] = lambda: sim_robot(5, 5)
    yield directory
    await directory.aclose()


async def test_the_embedded_store_keeps_registrations_in_memory() -> None:
    store = EmbeddedStore()
    assert isinstance(store, RegistryStore)
    assert (store.shared, store.location, store.read_only) == (False, EMBEDDED, "")
    await store.start()
    await store.save("cam", "tcp://127.0.0.1:7000", {"type": "camera"})
    await store.drop("nobody")  # not kept: no error
    assert await store.load() == []  # nothing to load without a file: memory starts empty
    await store.aclose()


async def test_the_embedded_store_writes_its_file_and_reads_it_back(tmp_path: Path) -> None:
    path = tmp_path / "state" / "registrations.json"
    store = EmbeddedStore(path)
    assert await store.load() == []  # no file yet
    await store.save("cam", "tcp://127.0.0.1:7000", {"type": "camera"})
    await store.save("lamp", "tcp://127.0.0.1:7001", {})
    await store.drop("lamp")
    await store.aclose()  # writes what is waiting
    assert json.loads(path.read_text()) == {
        "services": {"cam": {"url": "tcp://127.0.0.1:7000", "options": {"type": "camera"}}}
    }
    again = EmbeddedStore(path)
    assert await again.load() == [("cam", "tcp://127.0.0.1:7000", {"type": "camera"})]
    # What was loaded is kept: a later write keeps it too.
    await again.save("lamp", "tcp://127.0.0.1:7001", {})
    await again.aclose()
    assert sorted(json.loads(path.read_text())["services"]) == ["cam", "lamp"]


def test_a_registration_value_round_trips_and_bad_ones_are_named() -> None:
    text = encode_registration("tcp://127.0.0.1:7000", {"type": "camera"})
    assert json.loads(text) == {"url": "tcp://127.0.0.1:7000", "options": {"type": "camera"}}
    assert decode_registration(text) == ("tcp://127.0.0.1:7000", {"type": "camera"})
    assert decode_registration('{"url": "grpc://h:1/x"}') == ("grpc://h:1/x", {})
    for bad in ("", "[]", '{"options": {}}', '{"url": 3}', '{"url": "x", "options": []}'):
        with pytest.raises(ValueError, match="not a registration"):
            decode_registration(bad)


async def test_the_registry_says_its_store_is_embedded(world: MemoryDirectory) -> None:
    registry = Registry(directory=world, period=0)
    service = RegistryService(registry)
    await world.add("registry", service)
    assert await service.get("store") == "embedded"
    assert "store" in (await service.get("properties")).strip("()").split()
    with pytest.raises(PropertyError) as info:
        await service.set("store", "etcd://127.0.0.1:2379")
    assert info.value.code is Code.FAILED_PRECONDITION


async def test_a_read_only_store_refuses_registrations_and_says_why(world: MemoryDirectory) -> None:
    port = free_port()
    # A shared store that has not reached etcd yet: read-only, with its reason.
    store = EtcdStore(parse_store_url(f"etcd://127.0.0.1:{port}"), gateway_id="gw-a")
    registry = Registry(directory=world, period=0, store=store)
    service = RegistryService(registry)
    await world.add("registry", service)
    reason = f"etcd at 127.0.0.1:{port} cannot be reached (not connected yet)"
    assert await service.get("store") == f"etcd://127.0.0.1:{port} (read-only: {reason})"

    with pytest.raises(PropertyError) as info:
        await service.set("services.scout1", "tcp://127.0.0.1:7001")
    assert info.value.code is Code.UNAVAILABLE
    assert info.value.message == f"registering 'scout1': the registry is read-only: {reason}"
    assert "scout1" not in world.names(), "nothing is opened for a registration the store cannot keep"

    # A service it serves (a proxy the gateway opened) cannot be unregistered either.
    await world.register("lamp", "tcp://127.0.0.1:7001")
    with pytest.raises(PropertyError) as info:
        await service.set("services.lamp", "")
    assert info.value.code is Code.UNAVAILABLE
    assert "unregistering 'lamp': the registry is read-only" in info.value.message
    assert "lamp" in world.names()
    await store.aclose()


def test_a_store_and_a_persist_file_are_not_both_taken(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgument, match="give a store or persist, not both"):
        Registry(store=EmbeddedStore(), persist=tmp_path / "r.json")
