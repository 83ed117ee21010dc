"""The storage service in one process (the test kit): how it is built, configured and followed."""

from __future__ import annotations

import asyncio
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from support.waiting import wait_until

from clients import Event, InvalidArgument, Unavailable
from gateway.config import loads_config
from gateway.testing import serve
from services.apps.catalog import build, create, needs_directory
from services.apps.simulators import SimSensor
from services.apps.storage import MAX_FILE_SIZE, Storage, StorageService
from services.kernel.core import LocalService
from services.kernel.core import serve as backend_for
from services.kernel.errors import InvalidArgument as ServiceInvalidArgument

WAIT = 10.0


async def next_event(events: AsyncIterator[Event]) -> Event:
    return await asyncio.wait_for(anext(events), WAIT)


def test_a_storage_is_served_by_its_own_backend(tmp_path: Path) -> None:
    assert isinstance(backend_for(Storage(directory=str(tmp_path))), StorageService)
    assert type(backend_for(SimSensor())) is LocalService


def test_the_catalog_builds_a_storage_with_its_directory_option(tmp_path: Path) -> None:
    assert not needs_directory("storage") and needs_directory("group")
    made = build("storage", {"directory": str(tmp_path), "read_only": True})
    assert isinstance(made, Storage) and made.read_only and made.directory == str(tmp_path)
    with pytest.raises(ServiceInvalidArgument, match="missing a required argument: 'directory'"):
        create("storage")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ServiceInvalidArgument, match="exists and is not a directory"):
        build("storage", {"directory": str(tmp_path / "file")})
    for bad, why in (
        ({"max_file_size": MAX_FILE_SIZE + 1}, "max_file_size must be from 1 to"),
        ({"max_file_size": 0}, "max_file_size must be from 1 to"),
        ({"max_file_size": True}, "a whole number"),
        ({"read_only": "yes"}, "true or false"),
        ({"directory": 7}, "directory must be text"),
    ):
        with pytest.raises(ServiceInvalidArgument, match=why):
            build("storage", {"directory": str(tmp_path), **bad})


def test_a_relative_directory_starts_at_the_config_files_folder(tmp_path: Path) -> None:
    text = '[[services]]\nname = "files"\ntype = "storage"\noptions = { directory = "data/files" }\n'
    config = loads_config(text, "site.toml", tmp_path)
    assert config.services[0].options["directory"] == str(tmp_path / "data" / "files")
    absolute = text.replace("data/files", "/srv/files")
    assert loads_config(absolute, "site.toml", tmp_path).services[0].options["directory"] == "/srv/files"


async def test_the_directory_is_made_at_start(tmp_path: Path) -> None:
    where = tmp_path / "not" / "yet"
    async with serve(Storage(directory=str(where)), name="files") as client:
        assert where.is_dir()
        assert await client.get("files", "files") == "()"


async def test_a_followed_file_in_a_folder_moved_away_is_removed(tmp_path: Path) -> None:
    async with serve(Storage(directory=str(tmp_path)), name="files") as client:
        await client.set("files", "file", "v1", name="sub/a.txt")
        events = client.listen("files", "file", params={"name": "sub/a.txt"})
        try:
            assert (await next_event(events)).value == "v1"
            (tmp_path / "sub").rename(tmp_path / "elsewhere")
            gone = await next_event(events)
            assert gone.removed
            (tmp_path / "elsewhere").rename(tmp_path / "sub")
            assert (await next_event(events)).value == "v1"
        finally:
            await events.aclose()


async def test_a_wildcard_listen_skips_file_and_the_queries(tmp_path: Path) -> None:
    async with serve(Storage(directory=str(tmp_path)), name="files") as client:
        await client.set("files", "file", "x", name="a.txt")
        events = client.listen("files", "*")
        try:
            first = {(await next_event(events)).property for _ in range(5)}
            assert first == {"files", "directory", "max_file_size", "pattern", "read_only"}
        finally:
            await events.aclose()


async def test_a_pattern_selects_what_is_shown_and_stored(tmp_path: Path) -> None:
    (tmp_path / "keep.scxml").write_text("<scxml/>")
    (tmp_path / "other.log").write_text("log")
    async with serve(Storage(directory=str(tmp_path), pattern="*.scxml"), name="files") as client:
        assert await client.get_names("files", "files") == ["keep.scxml"]
        assert await client.get_names("files", "find") == ["keep.scxml"]
        with pytest.raises(InvalidArgument, match="only files matching"):
            await client.set("files", "file", "x", name="new.txt")
        await client.set("files", "file", "<scxml/>", name="charts/new.scxml")
        assert await client.get_names("files", "files") == ["charts/new.scxml", "keep.scxml"]


async def test_listens_of_one_file_share_and_leave(tmp_path: Path) -> None:
    storage = Storage(directory=str(tmp_path))
    async with serve(storage, name="files") as client:
        await client.set("files", "file", "v1", name="a.txt")
        first = client.listen("files", "file", params={"name": "a.txt"})
        second = client.listen("files", "file", params={"name": "a.txt"})
        try:
            assert (await next_event(first)).value == "v1"
            assert (await next_event(second)).value == "v1"
            await client.set("files", "file", "v2", name="a.txt")
            assert (await next_event(first)).value == "v2"
            assert (await next_event(second)).value == "v2"
        finally:
            await first.aclose()
            await second.aclose()
        # The last listen gone, the service follows the file no more.
        await wait_until(lambda: not storage._followed, what="the file is followed no more")


async def test_a_directory_removed_and_made_again_is_watched_again(tmp_path: Path) -> None:
    where = tmp_path / "store"
    async with serve(Storage(directory=str(where)), name="files") as client:
        await client.set("files", "file", "x", name="a.txt")
        events = client.listen("files", "files")
        try:
            assert (await next_event(events)).value == "(a.txt)"
            shutil.rmtree(where)
            assert (await next_event(events)).value == "()"
            with pytest.raises(Unavailable, match="cannot be opened"):
                await client.get("files", "file", name="a.txt")
            where.mkdir()
            (where / "b.txt").write_text("made by another program")
            assert (await next_event(events)).value == "(b.txt)"
        finally:
            await events.aclose()
