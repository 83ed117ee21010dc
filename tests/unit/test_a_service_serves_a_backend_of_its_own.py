"""A service that makes backends of its own (a replay's recorded services) serves them through the
directory it is handed: watchers hear them join and leave, and a taken name leaves the running one be."""

from __future__ import annotations

import pytest
from support.fake_backend import DictBackend

from gateway.engine.router import Router
from services.kernel.backend import Backend
from services.kernel.errors import AlreadyExists, InvalidArgument


async def test_a_backend_served_through_the_directory_joins_and_leaves_like_any_service() -> None:
    router = Router()
    heard: list[tuple[str, bool]] = []
    router.directory.watch(lambda name, backend: heard.append((name, backend is not None)))
    made = DictBackend({"location": "(1 2 0 0 0 0)"})
    await router.directory.serve("scout1", made)
    assert "scout1" in router.directory
    assert await router.backend("scout1").get("location") == "(1 2 0 0 0 0)"
    await router.directory.unregister("scout1")
    assert "scout1" not in router.directory
    assert made.closed
    assert heard == [("scout1", True), ("scout1", False)]


@pytest.mark.parametrize(("name", "refused"), [("scout1", AlreadyExists), ("bad name", InvalidArgument)])
async def test_a_backend_that_cannot_be_served_is_closed_and_the_running_one_stays(
    name: str, refused: type[Exception]
) -> None:
    router = Router()
    running: Backend = DictBackend({"speed": "0.5"})
    router.add("scout1", running)
    second = DictBackend({"speed": "9"})
    with pytest.raises(refused):
        await router.directory.serve(name, second)
    assert second.closed
    assert router.backend("scout1") is running
    assert router.names() == ["scout1"]
