"""Binary values through the HTTP front end of a real gateway process: base64 JSON, raw reads and
Sets, the live image stream, and what bad input gets. Every byte is checked against a gRPC call
of the same property (``tests/support/frames.py``: a camera of PNG frames and a writable picture).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import socket
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import grpc
import jwt
import pytest
from support.board import BOARD_TYPE
from support.frames import FRAMES_TYPE, SNAPSHOT_MAX, frame_png, solid_png
from support.gateway_process import GatewayProcess, StartGateway, start_gateway
from support.http_clients import http
from support.multipart import Part, PartReader, boundary_of
from support.sse import SseReader
from support.waiting import eventually

from bench import image_stream as image_stream_bench
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

__all__ = ["http"]

CONFIG = f"""
[[services]]
name = "cam"
type = "{FRAMES_TYPE}"
options = {{ rate_hz = 20.0 }}

[[services]]
name = "board"
type = "{BOARD_TYPE}"

[http]
max_streams_per_client = 6
"""

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def prop(service: str, path: str) -> str:
    return f"/api/v1/services/{service}/properties/{path}"


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_gateway(tmp_path_factory.mktemp("binary"), CONFIG)
    yield gw
    gw.stop()


@pytest.fixture
async def stub(gateway: GatewayProcess) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        yield pb_grpc.PropertyServiceStub(channel)


async def grpc_data(stub: pb_grpc.PropertyServiceStub, service: str, path: str) -> bytes:
    reply = await stub.Get(pb.GetRequest(service=service, property=path), timeout=10)
    assert reply.HasField("data"), reply
    return bytes(reply.data)


async def put_snapshot(stub: pb_grpc.PropertyServiceStub, data: bytes) -> None:
    await stub.Set(pb.SetRequest(service="cam", property="snapshot", data=data), timeout=10)


async def error_of(response: aiohttp.ClientResponse) -> dict[str, str]:
    body = await response.json()
    error: dict[str, str] = body["error"]
    return error


# -- JSON and raw reads --------------------------------------------------------------------------


async def test_a_binary_value_is_base64_json_byte_for_byte_what_grpc_reads(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    picture = solid_png(5, 3, (1, 2, 3))
    await put_snapshot(stub, picture)
    async with http.get(prop("cam", "snapshot")) as r:
        assert r.status == 200 and r.content_type == "application/json"
        body = await r.json()
    # ``time``: when the value was true (docs/recording.md, "Time of a value").
    assert set(body) == {"service", "path", "data", "media_type", "time"}
    assert body["media_type"] == "image/png"
    assert (
        base64.b64decode(body["data"], validate=True) == picture == await grpc_data(stub, "cam", "snapshot")
    )
    # A frame of the camera is a whole PNG; text values are unchanged.
    async with http.get(prop("cam", "camera.frame")) as r:
        frame = base64.b64decode((await r.json())["data"])
    assert frame.startswith(PNG_SIGNATURE)
    async with http.get(prop("cam", "count")) as r:
        assert set(await r.json()) == {"service", "path", "value", "time"}


async def test_the_model_names_media_type_and_max_size(http: aiohttp.ClientSession) -> None:
    async with http.get("/api/v1/services/cam/model") as r:
        model = {p["name"]: p for p in (await r.json())["properties"]}
    assert model["snapshot"]["type"] == "bytes"
    assert model["snapshot"]["media_type"] == "image/png"
    assert model["snapshot"]["max_size"] == SNAPSHOT_MAX
    assert model["camera.frame"]["media_type"] == "image/png"
    assert model["count"]["media_type"] is None and model["count"]["max_size"] is None


async def test_a_wildcard_get_carries_binary_values_as_base64(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    picture = solid_png(2, 2, (9, 9, 9))
    await put_snapshot(stub, picture)
    async with http.get(prop("cam", "*")) as r:
        values = {v["path"]: v for v in (await r.json())["values"]}
    assert base64.b64decode(values["snapshot"]["data"]) == picture
    assert values["snapshot"]["media_type"] == "image/png"
    assert "value" in values["count"] and "data" not in values["count"]


async def test_a_raw_read_answers_the_bytes_with_their_media_type(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    picture = solid_png(7, 7, (0, 200, 0))
    await put_snapshot(stub, picture)
    for query, headers in (("?raw=1", {}), ("?raw=true", {}), ("", {"Accept": "image/png"})):
        async with http.get(prop("cam", "snapshot") + query, headers=headers) as r:
            assert r.status == 200
            assert r.headers["Content-Type"] == "image/png"
            assert r.headers["X-Content-Type-Options"] == "nosniff"
            assert "sandbox" in r.headers["Content-Security-Policy"]
            assert await r.read() == picture
    # A browser's Accept (*/*) still gets JSON; a raw read of text is text/plain.
    async with http.get(prop("cam", "snapshot"), headers={"Accept": "text/html,*/*;q=0.8"}) as r:
        assert r.content_type == "application/json"
    async with http.get(prop("board", "note") + "?raw=1") as r:
        assert r.content_type == "text/plain" and r.charset == "utf-8"


# -- Sets ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("content_type", ["image/png", "application/octet-stream"])
async def test_a_raw_set_writes_the_bytes(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub, content_type: str
) -> None:
    picture = solid_png(6, 2, (10, 20, 30))
    async with http.put(prop("cam", "snapshot"), data=picture, headers={"Content-Type": content_type}) as r:
        assert r.status == 200, await r.text()
    assert await grpc_data(stub, "cam", "snapshot") == picture


async def test_a_json_set_of_base64_writes_the_bytes(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    picture = solid_png(3, 8, (200, 100, 0))
    body = {"data": base64.b64encode(picture).decode()}
    async with http.post(prop("cam", "snapshot"), json=body) as r:
        assert r.status == 200, await r.text()
    assert await grpc_data(stub, "cam", "snapshot") == picture


async def test_an_action_that_takes_bytes_takes_them_raw_or_in_base64(http: aiohttp.ClientSession) -> None:
    headers = {"Content-Type": "application/octet-stream"}
    async with http.post(prop("cam", "weigh"), data=b"\x07" * 300, headers=headers) as r:
        assert r.status == 200, await r.text()
        assert (await r.json())["value"] == "(300 7)"
    async with http.post(prop("cam", "weigh"), json={"data": base64.b64encode(b"\x09\x00").decode()}) as r:
        assert (await r.json())["value"] == "(2 9)"


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"data": "not base64!"}, "base64"),
        ({"data": "QUJD\nREVG"}, "base64"),
        ({"data": 12}, "base64"),
        ({"data": "QUJD", "value": "x"}, "both"),
        ({"value": "text"}, "bytes"),
    ],
)
async def test_a_bad_json_set_of_bytes_is_invalid_argument(
    http: aiohttp.ClientSession, body: dict[str, Any], words: str
) -> None:
    async with http.put(prop("cam", "snapshot"), json=body) as r:
        assert r.status == 400
        error = await error_of(r)
    assert error["code"] == "INVALID_ARGUMENT" and words in error["message"], error


@pytest.mark.parametrize(
    ("path", "content_type", "words"),
    [
        ("snapshot", "image/jpeg", "image/png or application/octet-stream"),
        ("snapshot", "text/plain", "Content-Type: application/json"),
        ("snapshot", "application/x-www-form-urlencoded", "Content-Type: application/json"),
        ("note", "application/octet-stream", "not a binary property"),
    ],
)
async def test_a_raw_set_with_the_wrong_content_type_is_refused(
    http: aiohttp.ClientSession, path: str, content_type: str, words: str
) -> None:
    service = "board" if path == "note" else "cam"
    async with http.put(prop(service, path), data=b"\x00\x01", headers={"Content-Type": content_type}) as r:
        assert r.status == 400
        error = await error_of(r)
    assert error["code"] == "INVALID_ARGUMENT" and words in error["message"], error


async def test_a_value_over_max_size_is_413_resource_exhausted(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    before = await grpc_data(stub, "cam", "snapshot")
    too_big = bytes(SNAPSHOT_MAX + 1)
    async with http.put(prop("cam", "snapshot"), data=too_big, headers={"Content-Type": "image/png"}) as r:
        assert r.status == 413
        error = await error_of(r)
    assert error["code"] == "RESOURCE_EXHAUSTED" and str(SNAPSHOT_MAX) in error["message"], error
    body = {"data": base64.b64encode(too_big).decode()}
    async with http.put(prop("cam", "snapshot"), json=body) as r:
        assert r.status == 413
        error = await error_of(r)
    assert str(SNAPSHOT_MAX) in error["message"] and str(SNAPSHOT_MAX + 1) in error["message"], error
    assert await grpc_data(stub, "cam", "snapshot") == before


# -- Server-Sent Events ----------------------------------------------------------------------------


async def test_an_event_carries_base64_data_and_media_type(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    first = solid_png(2, 3, (1, 1, 1))
    second = solid_png(3, 2, (2, 2, 2))
    await put_snapshot(stub, first)
    async with http.get("/api/v1/events", params={"sel": "cam/snapshot"}) as r:
        events = SseReader(r)
        [current] = await events.values_until_sync()
        assert current.data["media_type"] == "image/png" and "value" not in current.data
        assert base64.b64decode(current.data["data"]) == first
        await put_snapshot(stub, second)
        change = await events.until("value")
        assert base64.b64decode(change.data["data"]) == second


# -- the live image stream -------------------------------------------------------------------------


def frames_up_to(count: int) -> dict[bytes, int]:
    """Every frame the test camera has made by frame ``count``, and its number."""
    return {frame_png(n): n for n in range(count + 1)}


async def test_a_stream_is_one_part_per_frame_byte_for_byte(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    parts: list[Part] = []
    async with http.get(prop("cam", "camera.frame") + "/stream") as r:
        assert r.status == 200
        assert r.headers["Content-Type"].startswith("multipart/x-mixed-replace")
        reader = PartReader(r.content, boundary_of(r.headers["Content-Type"]))
        for _ in range(8):
            part = await reader.next()
            assert part is not None
            parts.append(part)
    count = int((await stub.Get(pb.GetRequest(service="cam", property="count"), timeout=10)).value)
    made = frames_up_to(count + 1)
    numbers = [made.get(part.body) for part in parts]
    assert None not in numbers, "every part is a frame the camera made, byte for byte"
    assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers), numbers
    assert all(part.headers["content-type"] == "image/png" for part in parts)
    sequences = [part.sequence for part in parts]
    assert sequences == sorted(sequences)


async def test_a_stream_ends_cleanly_when_the_property_goes(
    http: aiohttp.ClientSession, stub: pb_grpc.PropertyServiceStub
) -> None:
    try:
        async with http.get(prop("cam", "camera.frame") + "/stream") as r:
            reader = PartReader(r.content, boundary_of(r.headers["Content-Type"]))
            assert await reader.next() is not None
            await stub.Set(pb.SetRequest(service="cam", property="unplug"), timeout=10)
            while (part := await reader.next()) is not None:
                assert part.body.startswith(PNG_SIGNATURE)
            assert await r.content.read() == b""
        async with http.get(prop("cam", "camera.frame") + "/stream") as r:
            assert r.status == 404
            assert (await error_of(r))["code"] == "NOT_FOUND"
    finally:
        await stub.Set(pb.SetRequest(service="cam", property="plug"), timeout=10)


@pytest.mark.parametrize(
    ("path", "status", "code"),
    [
        ("count", 400, "INVALID_ARGUMENT"),
        ("nosuch", 404, "NOT_FOUND"),
        ("camera.*", 400, "INVALID_ARGUMENT"),
    ],
)
async def test_a_stream_of_what_is_not_one_binary_property_is_refused(
    http: aiohttp.ClientSession, path: str, status: int, code: str
) -> None:
    async with http.get(prop("cam", path) + "/stream") as r:
        assert r.status == status
        assert (await error_of(r))["code"] == code


async def test_streams_share_the_per_client_bound_with_event_streams(gateway: GatewayProcess) -> None:
    url = gateway.http_url.rstrip("/")
    async with aiohttp.ClientSession() as session, contextlib.AsyncExitStack() as stack:
        for n in range(6):
            route = "/api/v1/events?sel=cam/count" if n % 2 else prop("cam", "camera.frame") + "/stream"
            response = await stack.enter_async_context(session.get(url + route))
            assert response.status == 200
        async with session.get(url + prop("cam", "camera.frame") + "/stream") as r:
            assert r.status == 429
            error = await error_of(r)
        assert error["code"] == "RESOURCE_EXHAUSTED" and "http.max_streams_per_client" in error["message"]
        async with session.get(url + "/api/v1/events?sel=cam/count") as r:
            assert r.status == 429


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


async def test_a_slow_reader_gets_conflated_frames_and_memory_stays_flat(
    gateway_process: StartGateway,
) -> None:
    """A 256×256 camera of incompressible frames (197 KB each) at 25 Hz: a reader that stops for
    6 s would have 30 MB waiting if frames queued; it gets the latest ones, and the gateway's
    resident memory grows by less than a third of that."""
    gw = gateway_process(
        f'[[services]]\nname = "cam"\ntype = "{FRAMES_TYPE}"\n'
        "options = { rate_hz = 25.0, width = 256, height = 256, noisy = true }\n"
    )
    host, port = gw.http_address.rsplit(":", 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    await loop.sock_connect(sock, (host, int(port)))
    try:
        reader, writer = await asyncio.open_connection(sock=sock, limit=1 << 20)
        writer.write(
            f"GET {prop('cam', 'camera.frame')}/stream HTTP/1.1\r\nHost: {gw.http_address}\r\n\r\n".encode()
        )
        await writer.drain()
        status = await reader.readline()
        assert b" 200 " in status, status
        while (await reader.readline()) not in (b"\r\n", b""):
            pass  # headers: the body is chunked
        await asyncio.sleep(1.0)  # warm: the stream and its buffers are in place
        before = rss_bytes(gw.proc.pid)
        await asyncio.sleep(6.0)  # 150 frames made, none read
        during = rss_bytes(gw.proc.pid)
        assert during - before < 10 * 1024 * 1024, (before, during)
        # Reading again: the parts come with frames skipped, never a backlog of every one.
        body = await read_chunked(reader, 64 * 1024 * 1024)
        parts = PartReader(_Bytes(body), "psframe")
        seen = []
        with contextlib.suppress(AssertionError, asyncio.IncompleteReadError):
            while (part := await parts.next(within=1.0)) is not None:
                seen.append(part)
        assert seen, "parts arrive once the reader reads"
        skipped = sum(part.conflated for part in seen)
        gaps = sum(b.sequence - a.sequence - 1 for a, b in itertools.pairwise(seen))
        assert skipped > 0 or gaps > 0, [(p.sequence, p.conflated) for p in seen]
        assert len(seen) < 150
        print(
            f"gateway RSS {before / 2**20:.1f} MiB -> {during / 2**20:.1f} MiB while the reader stalled 6 s;"
            f" {len(seen)} parts read after, {skipped} conflated, {gaps} sequence gaps"
        )
        writer.close()
    finally:
        sock.close()


async def read_chunked(reader: asyncio.StreamReader, most: int) -> bytes:
    """The chunked body's bytes as they come, for about 3 s or ``most`` bytes."""
    out = bytearray()
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(3.0):
            while len(out) < most:
                size = int((await reader.readline()).strip(), 16)
                if size == 0:
                    break
                out += await reader.readexactly(size)
                await reader.readexactly(2)
    return bytes(out)


class _Bytes:
    """Bytes read as a stream (what :class:`PartReader` reads)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.at = 0

    async def readline(self) -> bytes:
        end = self.data.find(b"\n", self.at)
        if end < 0:
            raise asyncio.IncompleteReadError(self.data[self.at :], None)
        line, self.at = self.data[self.at : end + 1], end + 1
        return line

    async def readexactly(self, n: int) -> bytes:
        if self.at + n > len(self.data):
            raise asyncio.IncompleteReadError(self.data[self.at :], n)
        chunk, self.at = self.data[self.at : self.at + n], self.at + n
        return chunk


async def test_the_frames_are_the_cameras_own(stub: pb_grpc.PropertyServiceStub) -> None:
    """A frame read by gRPC is one the camera made: the stream's byte-for-byte check holds."""

    async def latest() -> bytes:
        return await grpc_data(stub, "cam", "camera.frame")

    frame = await eventually(latest, lambda data: data.startswith(PNG_SIGNATURE))
    count = int((await stub.Get(pb.GetRequest(service="cam", property="count"), timeout=10)).value)
    assert frame in frames_up_to(count + 1)


# -- rules -----------------------------------------------------------------------------------------

SECRET = "a shared secret of the lab, long enough for HS256"
RULES = f"""
[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[services]]
name = "cam"
type = "{FRAMES_TYPE}"
options = {{ rate_hz = 20.0 }}

[[rules]]
subject = "viewer"
service = "cam"
path = "camera.frame"
operations = ["read"]
effect = "permit"

[[rules]]
subject = "editor"
service = "cam"
path = "snapshot"
operations = ["read", "write"]
effect = "permit"
"""


def bearer(subject: str) -> dict[str, str]:
    claims = {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}
    return {"Authorization": f"Bearer {jwt.encode(claims, SECRET, algorithm='HS256')}"}


async def test_the_rules_decide_on_the_property_not_the_whole_service(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    """A caller allowed one binary property (and not the service's model) streams, reads and sets it
    with its media type; one allowed nothing is refused before any part or any byte is read."""
    (tmp_path / "jwt.secret").write_text(SECRET)
    gw = gateway_process(RULES)
    picture = solid_png(3, 3, (5, 6, 7))
    async with aiohttp.ClientSession(base_url=gw.http_url) as session:
        async with session.get(prop("cam", "camera.frame") + "/stream", headers=bearer("viewer")) as r:
            assert r.status == 200
            part = await PartReader(r.content, boundary_of(r.headers["Content-Type"])).next()
            assert part is not None and part.body.startswith(PNG_SIGNATURE)
        async with session.get(prop("cam", "camera.frame"), headers=bearer("viewer")) as r:
            assert (await r.json())["media_type"] == "image/png"
        async with session.get(prop("cam", "snapshot") + "/stream", headers=bearer("viewer")) as r:
            assert r.status == 403
        headers = {**bearer("editor"), "Content-Type": "image/png"}
        async with session.put(prop("cam", "snapshot"), data=picture, headers=headers) as r:
            assert r.status == 200, await r.text()
        async with session.get(prop("cam", "snapshot") + "?raw=1", headers=bearer("editor")) as r:
            assert r.headers["Content-Type"] == "image/png" and await r.read() == picture
        headers = {**bearer("viewer"), "Content-Type": "image/png"}
        async with session.put(prop("cam", "snapshot"), data=picture, headers=headers) as r:
            assert r.status == 403
            assert (await error_of(r))["code"] == "PERMISSION_DENIED"


async def test_the_image_stream_bench_runs() -> None:
    """``python -m bench.image_stream`` at a small size: every reader gets parts, the figures are there."""
    result = await image_stream_bench.run(readers=2, rate=20.0, frame_bytes=1000, seconds=0.5)
    assert result["readers"] == 2 and result["made_per_s"] > 0
    assert result["frames_per_s_per_reader"]["min"] > 0
    assert {"gateway_cpu_of_one_core", "conflated", "mbytes_per_s"} <= set(result)


async def test_a_reader_that_reads_nothing_is_cut_after_the_write_timeout(
    gateway_process: StartGateway,
) -> None:
    """A 25 Hz camera of 197 KB frames and a client that never reads: once a write has waited
    ``http.write_timeout`` the gateway drops the connection (logged), and another reader goes on."""
    gw = gateway_process(
        f'[[services]]\nname = "cam"\ntype = "{FRAMES_TYPE}"\n'
        "options = { rate_hz = 25.0, width = 256, height = 256, noisy = true }\n"
        "[http]\nwrite_timeout = 1.0\n"
    )
    host, port = gw.http_address.rsplit(":", 1)
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.connect((host, int(port)))
    request = f"GET {prop('cam', 'camera.frame')}/stream HTTP/1.1\r\nHost: {gw.http_address}\r\n\r\n"
    stalled.sendall(request.encode())
    try:

        async def output() -> str:
            return gw.output

        await eventually(output, lambda out: "http.write_timeout" in out, within=30)
        assert "image stream to 127.0.0.1 ended" in gw.output
        assert "Traceback" not in gw.output
        async with (
            aiohttp.ClientSession(base_url=gw.http_url) as session,
            session.get(prop("cam", "camera.frame") + "/stream") as r,
        ):
            part = await PartReader(r.content, boundary_of(r.headers["Content-Type"])).next()
            assert part is not None and part.body.startswith(PNG_SIGNATURE)
        # The cut connection comes to its end: what was buffered, then EOF (or a reset).
        stalled.setblocking(False)
        loop = asyncio.get_running_loop()
        async with asyncio.timeout(20):
            while True:
                try:
                    chunk = await loop.sock_recv(stalled, 1 << 20)
                except ConnectionResetError:
                    break
                if not chunk:
                    break
    finally:
        stalled.close()


async def test_a_stream_ends_with_its_closing_boundary_when_the_gateway_stops(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process(f'[[services]]\nname = "cam"\ntype = "{FRAMES_TYPE}"\n')
    async with (
        aiohttp.ClientSession(base_url=gw.http_url) as session,
        session.get(prop("cam", "camera.frame") + "/stream") as r,
    ):
        reader = PartReader(r.content, boundary_of(r.headers["Content-Type"]))
        assert await reader.next() is not None
        stopped = asyncio.get_running_loop().run_in_executor(None, gw.stop)
        while (part := await reader.next()) is not None:
            assert part.body.startswith(PNG_SIGNATURE)
        assert await stopped == 0
    assert "Traceback" not in gw.output
