"""Seeks of a replay, in this process over a directory in memory: wherever a seek comes from (the
start, the position before it, a later position), the services hold the values recorded there."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from support.group_support import MemoryDirectory
from support.recordings import ROBOT, Recorded, swarm_recording, write_recording

from services.apps.replay import Replay, ReplayedService
from services.kernel.backend import Backend, Change
from services.kernel.core import serve
from services.kernel.errors import NotFound, Unavailable
from services.kernel.values import Value


def held(directory: MemoryDirectory) -> dict[tuple[str, str], Value]:
    values: dict[tuple[str, str], Value] = {}
    for name, backend in directory.backends.items():
        assert isinstance(backend, ReplayedService)
        values.update(((name, path), value) for path, value in backend.values().items())
    return values


async def replaying(recording: Path) -> tuple[MemoryDirectory, Backend]:
    directory = MemoryDirectory()
    replay = serve(Replay(recording=str(recording), directory=directory, autostart=False))
    await replay.start()
    return directory, replay


@pytest.fixture
async def swarm(tmp_path: Path) -> AsyncIterator[tuple[MemoryDirectory, Backend]]:
    directory, replay = await replaying(swarm_recording(tmp_path))
    yield directory, replay
    await replay.aclose()


async def test_a_chain_of_seeks_holds_what_one_seek_from_the_start_holds(
    tmp_path: Path, swarm: tuple[MemoryDirectory, Backend]
) -> None:
    chained, replay = swarm
    for position in ("0.3", "2.6", "2.6", "3.55", "4.1", "1.05", "0", "3.5"):
        await replay.set("seek", position)
        fresh, once = await replaying(tmp_path / "swarm")
        await once.set("seek", position)
        assert held(chained) == held(fresh), position
        await once.aclose()


async def test_a_property_removed_in_the_recording_is_not_found_until_a_seek_goes_back_before(
    swarm: tuple[MemoryDirectory, Backend],
) -> None:
    directory, replay = swarm
    scout2 = directory.backends["scout2"]
    await replay.set("seek", "3.6")
    with pytest.raises(NotFound, match="removed"):
        await scout2.get("status")
    assert "status" not in [p.name for p in await scout2.match_properties("*")]
    await replay.set("seek", "4")
    with pytest.raises(NotFound):
        await scout2.get("status")
    await replay.set("seek", "2")
    assert await scout2.get("status") == "driving"
    assert "status" in [p.name for p in await scout2.match_properties("*")]


async def test_a_seek_back_before_a_first_value_tells_listeners_it_is_gone_and_gets_are_unavailable(
    tmp_path: Path,
) -> None:
    recording = write_recording(
        tmp_path,
        "late",
        {"rover": ROBOT},
        [Recorded("rover", "speed", "0.5", 0.0), Recorded("rover", "status", "out", 1.0)],
    )
    directory, replay = await replaying(recording)
    rover = directory.backends["rover"]
    with pytest.raises(Unavailable, match=r"no value of it is recorded before 0\.000 s"):
        await rover.get("status")
    await replay.set("seek", "1")
    assert await rover.get("status") == "out"
    heard: list[Change] = []
    await rover.listen("status", heard.append)
    await replay.set("seek", "0.5")
    assert heard == [Change("status", "", gap=True, removed=True)]
    with pytest.raises(Unavailable):
        await rover.get("status")
    await replay.aclose()
    assert directory.backends == {}
