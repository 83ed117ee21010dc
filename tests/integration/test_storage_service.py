"""A storage service in a real gateway process: files as properties, called as a user would."""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import sys
import textwrap
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from support.gateway_process import ROOT, GatewayProcess, StartGateway
from support.waiting import eventually

from clients import (
    AsyncClient,
    Event,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    ResourceExhausted,
)
from services.apps.storage import MAX_FILE_SIZE

WAIT = 10.0


def storage_config(options: str = "") -> str:
    # A relative directory: taken from the config file's folder (the test's tmp_path).
    return f"""
        [[services]]
        name = "files"
        type = "storage"
        options = {{ directory = "store"{", " + options if options else ""} }}
    """


@pytest.fixture
async def client(gateway_process: StartGateway) -> AsyncIterator[AsyncClient]:
    gw = gateway_process(storage_config())
    async with AsyncClient(gw.address, timeout=WAIT) as c:
        yield c


async def next_event(events: AsyncIterator[Event]) -> Event:
    return await asyncio.wait_for(anext(events), WAIT)


async def test_text_files_round_trip(client: AsyncClient, tmp_path: Path) -> None:
    store = tmp_path / "store"
    assert await client.get("files", "directory") == str(store)
    texts = {
        "notes.txt": "one line",
        "charts/door.scxml": "<scxml>\n  <state id='closed'/>\n</scxml>\n",
        "deep/a/b/c.json": '{"ünïcode": "名前", "tab": "\\t"}',
        "crlf.txt": "a\r\nb\r\n",
    }
    for name, text in texts.items():
        assert await client.set("files", "file", text, name=name) == ""
    for name, text in texts.items():
        assert await client.get("files", "file", name=name) == text
        assert (store / name).read_bytes().decode("utf-8") == text
    assert await client.get_names("files", "files") == sorted(texts)
    info = await client.get_marker("files", "info", name="charts/door.scxml")
    assert info.fields["size"] == str(len(texts["charts/door.scxml"].encode()))
    assert info.fields["mtime"].endswith("Z")
    assert info.fields["type"] in ("application/octet-stream", "application/xml", "text/xml")
    assert (await client.get_marker("files", "info", name="notes.txt")).fields["type"] == "text/plain"
    assert await client.get_names("files", "find", pattern="*.txt") == ["crlf.txt", "notes.txt"]
    assert await client.get_names("files", "find", min_size="20") == ["charts/door.scxml", "deep/a/b/c.json"]
    assert await client.get_names("files", "find", newer="2000-01-01T00:00:00Z", max_size="8") == [
        "crlf.txt",
        "notes.txt",
    ]
    assert await client.get_names("files", "find", older="2000-01-01T00:00:00Z") == []

    await client.set("files", "file", "", name="notes.txt")
    await client.set("files", "remove", "", name="crlf.txt")
    assert not (store / "notes.txt").exists() and not (store / "crlf.txt").exists()
    assert await client.get_names("files", "files") == ["charts/door.scxml", "deep/a/b/c.json"]
    with pytest.raises(NotFound):
        await client.get("files", "file", name="notes.txt")
    with pytest.raises(NotFound):
        await client.set("files", "remove", "", name="notes.txt")


async def test_the_model_and_the_parameters(client: AsyncClient) -> None:
    model = await client.describe("files")
    by_name = {p.name: p for p in model.properties}
    assert by_name["file"].access.value == "read-write"
    assert [(p.name, p.required) for p in by_name["file"].parameters] == [("name", True)]
    assert by_name["remove"].access.value == "action" and by_name["find"].access.value == "query"
    assert await client.get("files", "file.parameters") == "((name text -))"
    # A wildcard Get reads the values, never `file` (it needs its name) nor the queries.
    assert set(await client.get_matching("files", "*")) == {
        "files",
        "directory",
        "max_file_size",
        "pattern",
        "read_only",
    }
    with pytest.raises(InvalidArgument, match="needs the parameter `name`"):
        await client.get("files", "file")
    with pytest.raises(InvalidArgument, match="no parameter `colour`"):
        await client.set("files", "file", "x", name="a.txt", colour="red")


async def test_a_binary_file_is_read_written_and_followed_as_bytes(
    client: AsyncClient, tmp_path: Path
) -> None:
    store = tmp_path / "store"
    png = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 40  # not UTF-8
    assert await client.set("files", "blob", png, name="pics/a.png") == ""
    assert (store / "pics" / "a.png").read_bytes() == png
    assert await client.get("files", "blob", name="pics/a.png") == png
    assert await client.get("files", "blob.media_type", name="pics/a.png") == "image/png"
    assert await client.get("files", "blob.parameters") == "((name text -))"
    model = {p.name: p for p in (await client.describe("files")).properties}
    assert (model["blob"].type, model["blob"].access.value) == ("bytes", "read-write")
    assert model["blob"].max_size == MAX_FILE_SIZE
    # A text file reads as bytes too; text and bytes are each refused where the other belongs.
    await client.set("files", "file", "héllo", name="t.txt")
    assert await client.get("files", "blob", name="t.txt") == "héllo".encode()
    with pytest.raises(InvalidArgument, match="Set `blob`"):
        await client.set("files", "file", b"\x00\x01", name="t.txt")
    with pytest.raises(InvalidArgument, match="send its value as bytes"):
        await client.set("files", "blob", "text", name="t.bin")
    # An empty binary value is an empty file.
    await client.set("files", "blob", b"", name="empty.bin")
    assert (store / "empty.bin").read_bytes() == b""
    assert await client.get("files", "blob", name="empty.bin") == b""

    events = client.listen("files", "blob", params={"name": "pics/a.png"})
    try:
        first = await next_event(events)
        assert (first.property, first.value) == ("blob", png)
        await client.set("files", "blob", png[::-1], name="pics/a.png")
        assert (await next_event(events)).value == png[::-1]
        (store / "pics" / "a.png").write_bytes(b"\xff" * 10)  # another program writes it
        seen = await next_event(events)
        if seen.value == b"":  # written in place: the truncation may be seen first
            seen = await next_event(events)
        assert seen.value == b"\xff" * 10
        await client.set("files", "file", "now text", name="pics/a.png")
        assert (await next_event(events)).value == b"now text"
        assert await client.get("files", "file", name="pics/a.png") == "now text"
    finally:
        await events.aclose()


async def test_traversal_is_refused_and_nothing_outside_is_touched(
    client: AsyncClient, tmp_path: Path
) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("secret")
    store = tmp_path / "store"
    for name in ("../outside/secret.txt", "/etc/passwd", "a/../../outside/secret.txt", "./x", "a//b"):
        with pytest.raises(InvalidArgument, match="bad file name"):
            await client.get("files", "file", name=name)
        with pytest.raises(InvalidArgument, match="bad file name"):
            await client.set("files", "file", "planted", name=name)
        with pytest.raises(InvalidArgument, match="bad file name"):
            await client.get("files", "info", name=name)
    # A symbolic link planted on disk, to a folder and to a file outside.
    (store / "out").symlink_to(outside)
    (store / "passwd").symlink_to("/etc/passwd")
    for name in ("out/secret.txt", "passwd"):
        with pytest.raises(FailedPrecondition, match="symbolic link"):
            await client.get("files", "file", name=name)
        with pytest.raises(FailedPrecondition, match="symbolic link"):
            await client.set("files", "file", "planted", name=name)
    with pytest.raises(FailedPrecondition, match="symbolic link"):
        await client.set("files", "file", "planted", name="out/new.txt")
    assert sorted(p.name for p in outside.iterdir()) == ["secret.txt"]
    assert (outside / "secret.txt").read_text() == "secret"
    assert "passwd" not in await client.get_names("files", "files")


async def test_a_file_changed_on_disk_is_heard_by_a_listen(client: AsyncClient, tmp_path: Path) -> None:
    path = tmp_path / "store" / "state.txt"
    await client.set("files", "file", "idle", name="state.txt")
    events = client.listen("files", "file", params={"name": "state.txt"})
    try:
        first = await next_event(events)
        assert (first.property, first.value) == ("file", "idle")
        # Another process writes the file in place, then replaces it.
        other = await asyncio.create_subprocess_exec(
            sys.executable, "-c", f"open({str(path)!r}, 'w').write('running')"
        )
        assert await other.wait() == 0
        # Writing in place truncates first: a Listen may truly see the empty file before the text.
        written = await next_event(events)
        if written.value == "":
            written = await next_event(events)
        assert written.value == "running"
        await client.set("files", "file", "done", name="state.txt")
        assert (await next_event(events)).value == "done"
        path.unlink()
        gone = await next_event(events)
        assert gone.removed and gone.value == ""
        path.write_text("back")
        assert (await next_event(events)).value == "back"
    finally:
        await events.aclose()


async def test_files_follows_files_added_and_removed_on_disk(client: AsyncClient, tmp_path: Path) -> None:
    store = tmp_path / "store"
    events = client.listen("files", "files")
    try:
        assert (await next_event(events)).value == "()"
        (store / "sub").mkdir()
        (store / "sub" / "new.txt").write_text("from outside")
        assert (await next_event(events)).value == "(sub/new.txt)"
        await client.set("files", "file", "from a client", name="a.txt")
        assert (await next_event(events)).value == "(a.txt sub/new.txt)"
        shutil.rmtree(store / "sub")
        assert (await next_event(events)).value == "(a.txt)"
    finally:
        await events.aclose()


async def test_a_set_racing_readers_never_shows_half_a_file(client: AsyncClient, tmp_path: Path) -> None:
    size = 256 * 1024
    contents = ["a" * size, "b" * size]
    path = tmp_path / "store" / "race.txt"
    await client.set("files", "file", contents[0], name="race.txt")
    done = asyncio.Event()
    seen: list[str] = []

    async def writer() -> None:
        try:
            for i in range(40):
                await client.set("files", "file", contents[i % 2], name="race.txt")
        finally:
            done.set()

    async def gateway_reader() -> None:
        while not done.is_set():
            seen.append(await client.get("files", "file", name="race.txt"))

    def disk_reader() -> list[bytes]:
        read = []
        while not done.is_set():
            read.append(path.read_bytes())
        return read

    on_disk = asyncio.create_task(asyncio.to_thread(disk_reader))
    await asyncio.gather(writer(), gateway_reader(), gateway_reader())
    from_disk = await on_disk
    assert seen and from_disk
    assert all(text in contents for text in seen), {len(t) for t in seen}
    assert all(data.decode() in contents for data in from_disk), {len(d) for d in from_disk}
    assert [p.name for p in path.parent.iterdir()] == ["race.txt"]  # no temporary file left


async def test_sizes_binary_and_read_only(gateway_process: StartGateway, tmp_path: Path) -> None:
    gw = gateway_process(storage_config("max_file_size = 1000"))
    store = tmp_path / "store"
    async with AsyncClient(gw.address, timeout=WAIT) as c:
        assert await c.get("files", "max_file_size") == "1000"
        await c.set("files", "file", "x" * 1000, name="full.txt")
        with pytest.raises(ResourceExhausted, match="1001 bytes, over the limit of 1000"):
            await c.set("files", "file", "x" * 1001, name="big.txt")
        with pytest.raises(ResourceExhausted, match="over the limit"):
            await c.set("files", "file", "é" * 501, name="big.txt")  # 1002 bytes in UTF-8
        assert not (store / "big.txt").exists()
        (store / "huge.log").write_bytes(b"y" * 5000)
        with pytest.raises(ResourceExhausted, match="5000 bytes"):
            await c.get("files", "file", name="huge.log")
        (store / "photo.jpg").write_bytes(b"\xff\xd8\xff\xe0 not text")
        with pytest.raises(FailedPrecondition, match=r"read it as bytes with `blob`.*image/jpeg"):
            await c.get("files", "file", name="photo.jpg")
        assert await c.get("files", "blob", name="photo.jpg") == b"\xff\xd8\xff\xe0 not text"
        with pytest.raises(ResourceExhausted, match="1001 bytes, over the limit of 1000"):
            await c.set("files", "blob", b"\0" * 1001, name="big.bin")
        info = await c.get_marker("files", "info", name="photo.jpg")
        assert (info.fields["size"], info.fields["type"]) == ("13", "image/jpeg")

    read_only = tmp_path / "ro.toml"
    read_only.write_text(textwrap.dedent(storage_config('read_only = true, pattern = "*.txt"')))
    gw = GatewayProcess(
        [sys.executable, "-m", "gateway.cli", "serve", "--config", str(read_only), "--listen", "127.0.0.1:0"]
    )
    try:
        gw.wait_ready()
        async with AsyncClient(gw.address, timeout=WAIT) as c:
            assert await c.get_names("files", "files") == ["full.txt"]  # the pattern shows text files only
            with pytest.raises(NotFound, match="only files matching"):
                await c.get("files", "file", name="huge.log")
            with pytest.raises(FailedPrecondition, match="read-only"):
                await c.set("files", "file", "new", name="full.txt")
            assert await c.get("files", "file", name="full.txt") == "x" * 1000
    finally:
        gw.stop()


async def test_the_largest_file_travels_both_ways(gateway_process: StartGateway) -> None:
    gw = gateway_process(storage_config())
    text = "z" * MAX_FILE_SIZE
    async with AsyncClient(gw.address, timeout=30) as c:
        await c.set("files", "file", "small", name="max.txt")
        events = c.listen("files", "file", params={"name": "max.txt"})
        try:
            assert (await next_event(events)).value == "small"
            await c.set("files", "file", text, name="max.txt")
            assert await c.get("files", "file", name="max.txt") == text
            assert (await next_event(events)).value == text
        finally:
            await events.aclose()
        with pytest.raises(ResourceExhausted, match="max_file_size"):
            await c.set("files", "file", text + "z", name="max.txt")


def test_check_config_names_a_missing_directory(tmp_path: Path) -> None:
    config = tmp_path / "site.toml"
    config.write_text('[[services]]\nname = "files"\ntype = "storage"\noptions = { pattern = "*.txt" }\n')
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "check-config", str(config)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "services (files)" in done.stderr and "missing a required argument: 'directory'" in done.stderr


async def test_a_full_disk_is_resource_exhausted_through_the_gateway(tmp_path: Path) -> None:
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("a full disk needs a tiny tmpfs: unshare (util-linux) is not installed")
    store = tmp_path / "store"
    store.mkdir()
    probe = await asyncio.create_subprocess_exec(
        unshare, "-rm", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {store}", stderr=subprocess.PIPE
    )
    _, why = await probe.communicate()
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a tiny tmpfs in a user namespace here: {why.decode().strip()}")
    config = tmp_path / "full.toml"
    config.write_text(textwrap.dedent(storage_config()))
    serve = f"mount -t tmpfs -o size=256k tmpfs {store} && exec {sys.executable} -m gateway.cli serve"
    gw = GatewayProcess(
        [unshare, "-rm", "sh", "-c", f"{serve} --config {config} --listen 127.0.0.1:0"],
        env={"PYTHONPATH": str(ROOT)},
    )
    try:
        gw.wait_ready()
        async with AsyncClient(gw.address, timeout=WAIT) as c:
            await c.set("files", "file", "the old content", name="kept.txt")
            with pytest.raises(ResourceExhausted, match="the disk is full"):
                await c.set("files", "file", "x" * 1024 * 1024, name="kept.txt")
            assert await c.get("files", "file", name="kept.txt") == "the old content"
            assert await eventually(lambda: c.get_names("files", "files"), lambda v: v == ["kept.txt"])
    finally:
        gw.stop()
