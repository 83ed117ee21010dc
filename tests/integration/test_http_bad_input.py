"""Bad input to the HTTP front end of a real gateway process: each gets a clear error or is bounded,
and no other client notices.

Malformed and oversized bodies, unknown routes and methods, traversal out of the console's
folder (sent on a plain socket, exactly as written, so no client library tidies the path),
foreign origins and host names, a client that never reads its event stream, and more event
streams than the front end takes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
from collections.abc import AsyncIterator, Iterator
from typing import Any

import aiohttp
import psutil
import pytest
from support.board import BOARD_TYPE
from support.gateway_process import GatewayProcess, StartGateway, start_gateway
from support.http_clients import http
from support.sse import SseReader
from support.waiting import eventually

from clients import AsyncClient

__all__ = ["http"]  # fixtures used by name

CONFIG = f"""
[[services]]
name = "board"
type = "{BOARD_TYPE}"
"""
NOTE = "/api/v1/services/board/properties/note"
JSON = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_gateway(tmp_path_factory.mktemp("bad-input"), CONFIG)
    yield gw
    gw.stop()


def port_of(gw: GatewayProcess) -> int:
    return int(gw.http_address.rpartition(":")[2])


async def raw_request(port: int, head: str, body: bytes = b"") -> tuple[int, dict[str, str], bytes]:
    """Send ``head`` (request line and headers, without the blank line) as written; the answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(head.encode() + b"\r\nConnection: close\r\n\r\n" + body)
        await writer.drain()
        async with asyncio.timeout(10):
            answer = await reader.read()
    finally:
        writer.close()
    header_block, _, payload = answer.partition(b"\r\n\r\n")
    lines = header_block.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return int(lines[0].split()[1]), headers, payload


async def put(http: aiohttp.ClientSession, url: str, data: bytes, headers: dict[str, str]) -> tuple[int, Any]:
    async with http.put(url, data=data, headers=headers) as response:
        return response.status, await response.json()


async def test_a_body_announced_too_large_is_413_before_it_is_sent(gateway: GatewayProcess) -> None:
    """``Expect: 100-continue`` (curl sends it for bodies over 1 MB): 413 at once, no 100 Continue."""
    port = port_of(gateway)
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(
            (
                f"PUT {NOTE} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                f"Content-Length: {2 * 1024 * 1024}\r\nExpect: 100-continue\r\n\r\n"
            ).encode()
        )
        await writer.drain()
        async with asyncio.timeout(10):
            status_line = await reader.readline()
            head = (await reader.readuntil(b"\r\n\r\n")).decode("latin-1")
        assert status_line.split()[1] == b"413", f"the answer to the announced body: {status_line!r}"
        length = int(
            next(line for line in head.split("\r\n") if line.lower().startswith("content-length")).split(":")[
                1
            ]
        )
        async with asyncio.timeout(10):
            error = json.loads(await reader.readexactly(length))["error"]
        assert error["code"] == "RESOURCE_EXHAUSTED" and "http.max_body" in error["message"], error
    finally:
        writer.close()
    # An expectation the front end does not know is a JSON error too.
    head = (
        f"PUT {NOTE} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
        "Content-Length: 2\r\nExpect: bogus"
    )
    status, _, payload = await raw_request(port, head, b"{}")
    assert status == 417
    assert json.loads(payload)["error"]["code"] == "INVALID_ARGUMENT"


@pytest.mark.parametrize(
    ("body", "named"),
    [
        (b"{", "not valid JSON"),
        (b"", "not valid JSON"),
        (b'{"value": NaN}', "NaN"),
        (b"\xff\xfe\x00", "not UTF-8"),
        (b"\xc3(", "not"),
        (b'["value"]', "must be a JSON object"),
        (b"{}", "needs a 'value'"),
        (b'{"valu": "x"}', "unknown key 'valu'"),
        (b'{"value": null}', "not null"),
        (b'{"value": {"x": 1}}', "not an object"),
        (b'{"value": "x", "parameters": [1]}', "'parameters' must be a JSON object"),
        (b'{"value": [1, {"a": 2}]}', "cannot put a dict in a list"),
        (b"[" * 100_000 + b"]" * 100_000, "JSON"),
    ],
)
async def test_a_malformed_body_is_400_naming_what_is_wrong(
    http: aiohttp.ClientSession, body: bytes, named: str
) -> None:
    status, answer = await put(http, NOTE, body, JSON)
    assert status == 400, answer
    assert answer["error"]["code"] == "INVALID_ARGUMENT"
    assert named in answer["error"]["message"], answer


@pytest.mark.parametrize("content_type", ["text/plain", "application/x-www-form-urlencoded", None])
async def test_a_set_must_say_it_is_json(http: aiohttp.ClientSession, content_type: str | None) -> None:
    headers = {"Content-Type": content_type} if content_type else {}
    async with http.post(
        NOTE, data=b'{"value": "x"}', headers=headers, skip_auto_headers=["Content-Type"]
    ) as r:
        assert r.status == 400
        assert "Content-Type: application/json" in (await r.json())["error"]["message"]


async def test_an_oversized_body_is_413_and_the_value_unchanged(
    http: aiohttp.ClientSession, gateway: GatewayProcess
) -> None:
    async with AsyncClient(gateway.address, timeout=10) as client:
        await client.set("board", "note", "kept")
        big = json.dumps({"value": "x" * (1024 * 1024 + 10)}).encode()
        status, answer = await put(http, NOTE, big, JSON)
        assert status == 413
        assert (
            answer["error"]["code"] == "RESOURCE_EXHAUSTED" and "http.max_body" in answer["error"]["message"]
        )

        async def chunks() -> AsyncIterator[bytes]:  # no Content-Length: found while reading
            for _ in range(20):
                yield b" " * 100_000

        async with http.put(NOTE, data=chunks(), headers=JSON) as response:
            assert response.status == 413
            assert (await response.json())["error"]["code"] == "RESOURCE_EXHAUSTED"
        assert await client.get("board", "note") == "kept"


@pytest.mark.parametrize(
    ("method", "url", "expected"),
    [
        ("GET", "/api/v1/nothing", (404, "NOT_FOUND")),
        ("GET", "/api/v2/services", (404, "NOT_FOUND")),
        ("GET", "/api/v1/services/board/properties", (404, "NOT_FOUND")),
        ("DELETE", NOTE, (405, "UNIMPLEMENTED")),
        ("POST", "/api/v1/services", (405, "UNIMPLEMENTED")),
        ("PATCH", "/api/v1/events", (405, "UNIMPLEMENTED")),
    ],
)
async def test_unknown_routes_and_wrong_methods_are_json(
    http: aiohttp.ClientSession, method: str, url: str, expected: tuple[int, str]
) -> None:
    async with http.request(method, url, headers=JSON, data=b"{}") as response:
        body = await response.json()
        assert (response.status, body["error"]["code"]) == expected
        if response.status == 405:
            assert response.headers["Allow"]


@pytest.mark.parametrize(
    "path",
    [
        "/console/../../etc/passwd",
        "/console/../../../../../../etc/passwd",
        "/console/%2e%2e/%2e%2e/etc/passwd",
        "/console/%2E%2E%2F%2E%2E%2Fetc%2Fpasswd",
        "/console/..%2f..%2f..%2fetc%2fpasswd",
        "/console/....//....//etc/passwd",
        "/console/%252e%252e/etc/passwd",
        "/console/..\\..\\etc\\passwd",
        "/console/../http/front.py",
        "/console/%2e%2e/http/front.py",
        "/console/.hidden",
        "/console//etc/passwd",
        "/console/index.html%00.js",
        "/console/",
        "/console/index.html/",
        "/..%2f..%2fetc/passwd",
    ],
)
async def test_nothing_outside_the_console_folder_is_served(gateway: GatewayProcess, path: str) -> None:
    status, _, body = await raw_request(port_of(gateway), f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1")
    if path == "/console/":  # the folder itself is its index page, never a listing
        assert status == 200 and b"<html" in body.lower()
        return
    assert status == 404, (path, status, body[:200])
    assert b"root:" not in body and b"import" not in body


async def test_a_foreign_origin_is_refused_and_the_own_one_is_not(gateway: GatewayProcess) -> None:
    port = port_of(gateway)
    own = f"http://127.0.0.1:{port}"
    body = b'{"value": "from a page"}'
    for origin, expected in ((own, 200), ("http://evil.example", 403), ("null", 403), (f"{own}.evil", 403)):
        head = (
            f"PUT {NOTE} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nOrigin: {origin}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}"
        )
        status, headers, answer = await raw_request(port, head, body)
        assert status == expected, (origin, answer)
        assert "access-control-allow-origin" not in headers
        if expected == 403:
            assert json.loads(answer)["error"]["code"] == "PERMISSION_DENIED"


@pytest.mark.parametrize(
    ("host", "expected"),
    [
        ("127.0.0.1", 200),
        ("localhost:8080", 200),
        ("[::1]:80", 200),
        ("app.localhost", 200),
        ("evil.example", 403),
        ("evil.example:8080", 403),
        ("127.0.0.1.evil.example", 403),
        ("10.0.0.7", 403),
    ],
)
async def test_a_host_that_is_not_loopback_is_refused(
    gateway: GatewayProcess, host: str, expected: int
) -> None:
    status, _, body = await raw_request(port_of(gateway), f"GET /api/v1/health HTTP/1.1\r\nHost: {host}")
    assert status == expected, body
    if expected == 403:
        assert b"loopback" in body


async def test_a_reader_that_never_reads_is_conflated_and_slows_no_one(gateway: GatewayProcess) -> None:
    port = port_of(gateway)
    process = psutil.Process(gateway.proc.pid)
    big = "y" * 60_000
    # The slow client: a socket with a small receive buffer that asks for events, then reads nothing.
    slow = socket.socket()
    slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    slow.connect(("127.0.0.1", port))
    slow.sendall(f"GET /api/v1/events?sel=board/note HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    try:
        async with (
            AsyncClient(gateway.address, timeout=10) as client,
            aiohttp.ClientSession(base_url=gateway.http_url) as http,
            http.get("/api/v1/events", params={"sel": "board/note"}) as fast_response,
        ):
            fast = SseReader(fast_response)
            await fast.values_until_sync()
            await client.set("board", "note", big + "warm-up")
            await fast.until("value")
            before = process.memory_info().rss
            for i in range(1000):
                await client.set("board", "note", f"{big}{i}")
            # The reading client gets the last value while the other still reads nothing.
            last = await fast.until("value")
            while last.data["value"] != f"{big}999":
                last = await fast.until("value")
            grown = process.memory_info().rss - before
            # 1,000 values of 60 KB held for the slow reader would be 60 MB; conflated, one is held.
            assert grown < 20_000_000, f"the gateway grew by {grown} bytes"
            # The slow reader, reading at last, gets the latest value, not every one in between.
            slow.setblocking(False)
            loop = asyncio.get_running_loop()
            received = b""
            async with asyncio.timeout(20):
                while f'"{big}999"'.encode() not in received:
                    received += await loop.sock_recv(slow, 1 << 20)
            events = [
                json.loads(line[len(b"data: ") :])
                for line in received.split(b"\n")
                if line.startswith(b'data: {"service"')
            ]
            assert len(events) < 200, f"the slow reader got {len(events)} events of 1,001 values"
            assert max(event["conflated"] for event in events) > 0
            health = await http.get("/api/v1/health")
            assert health.status == 200
    finally:
        slow.close()


async def test_streams_beyond_max_streams_are_refused_and_nobody_else_notices(
    gateway_process: StartGateway,
) -> None:
    # Connections are capped per address too (256 by default): lifted here, the streams are the subject.
    gw = gateway_process(
        CONFIG
        + "\n[http]\nmax_streams = 256\nmax_streams_per_client = 1000\nmax_connections_per_address = 2000\n"
    )
    port = port_of(gw)
    request = f"GET /api/v1/events?sel=board/note HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode()
    connections: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []
    try:
        for _ in range(1000):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(request)
            connections.append((reader, writer))
        statuses = await asyncio.gather(*(first_line(reader) for reader, _ in connections))
        assert statuses.count(200) == 256
        assert statuses.count(503) == 1000 - 256
        async with (
            aiohttp.ClientSession(base_url=gw.http_url) as http,
            AsyncClient(gw.address, timeout=10) as client,
        ):
            async with http.get("/api/v1/events", params={"sel": "board/note"}) as refused:
                assert refused.status == 503
                error = (await refused.json())["error"]
                assert error["code"] == "RESOURCE_EXHAUSTED" and "http.max_streams" in error["message"]
            # Everyone else carries on: gRPC and the JSON routes answer, the idle streams get changes.
            await client.set("board", "note", "still here")
            async with http.get("/api/v1/services/board/properties/note") as got:
                assert (await got.json())["value"] == "still here"
            open_ones = [
                reader for (reader, _), status in zip(connections, statuses, strict=True) if status == 200
            ]
            await eventually(lambda: read_some(open_ones[0]), lambda text: b"still here" in text)
        # Closing the streams frees their places.
        for _, writer in connections:
            writer.close()
        async with aiohttp.ClientSession(base_url=gw.http_url) as http:

            async def opens() -> int:
                async with http.get("/api/v1/events", params={"sel": "board/note"}) as response:
                    return response.status

            await eventually(opens, lambda status: status == 200)
    finally:
        for _, writer in connections:
            with contextlib.suppress(Exception):
                writer.close()


async def first_line(reader: asyncio.StreamReader) -> int:
    async with asyncio.timeout(30):
        line = await reader.readline()
    return int(line.split()[1])


async def read_some(reader: asyncio.StreamReader) -> bytes:
    async with asyncio.timeout(1):
        return await reader.read(1 << 16)


async def test_a_reader_that_never_reads_does_not_hold_up_shutdown(gateway_process: StartGateway) -> None:
    gw = gateway_process(CONFIG)
    port = port_of(gw)
    slow = socket.socket()
    slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    slow.connect(("127.0.0.1", port))
    slow.sendall(f"GET /api/v1/events?sel=board/note HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    try:
        async with AsyncClient(gw.address, timeout=10) as client:
            for i in range(200):  # far more than the socket buffers hold: the writer is stuck in write
                await client.set("board", "note", f"{'z' * 60_000}{i}")
        assert await asyncio.to_thread(gw.stop) == 0  # SIGTERM: a clean exit, not the SIGKILL after 5 s
        assert "Traceback" not in gw.output
    finally:
        slow.close()


def stream_request(port: int) -> bytes:
    return f"GET /api/v1/events?sel=board/note HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode()


async def open_from(source: str, port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """An event-stream request sent from the loopback address ``source`` (one peer of several)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
    writer.write(stream_request(port))
    return reader, writer


async def error_of(reader: asyncio.StreamReader) -> tuple[int, dict[str, str]]:
    """The status and JSON error of a refused request (its whole answer)."""
    async with asyncio.timeout(30):
        answer = await reader.read(1 << 16)
    head, _, body = answer.partition(b"\r\n\r\n")
    return int(head.split()[1]), json.loads(body)["error"]


async def test_a_reader_that_never_reads_is_cut_after_the_write_deadline(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process(CONFIG + "\n[http]\nwrite_timeout = 1.0\n", ("--log-level", "info"))
    port = port_of(gw)
    slow = socket.socket()
    slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    slow.connect(("127.0.0.1", port))
    slow.sendall(stream_request(port))
    try:
        async with (
            AsyncClient(gw.address, timeout=10) as client,
            aiohttp.ClientSession(base_url=gw.http_url) as http,
            http.get("/api/v1/events", params={"sel": "board/note"}) as fast_response,
        ):
            fast = SseReader(fast_response)
            await fast.values_until_sync()
            # Far more than the sockets buffer: the slow stream's write waits, then passes its deadline.
            i = 0

            async def set_and_see() -> str:
                nonlocal i
                i += 1
                await client.set("board", "note", f"{'w' * 60_000}{i}")
                event = await fast.until("value")
                while not event.data["value"].endswith(f"w{i}"):
                    event = await fast.until("value")
                return gw.output

            await eventually(set_and_see, lambda out: "http.write_timeout" in out, within=30)
            assert "event stream to 127.0.0.1 ended" in gw.output
            assert "Traceback" not in gw.output
            # The reading client goes on.
            await client.set("board", "note", "after the cut")
            event = await fast.until("value")
            while event.data["value"] != "after the cut":
                event = await fast.until("value")
        # The cut stream's connection is closed: reading it comes to its end (what was buffered, then EOF).
        slow.setblocking(False)
        loop = asyncio.get_running_loop()
        async with asyncio.timeout(20):
            while True:
                try:
                    chunk = await loop.sock_recv(slow, 1 << 20)
                except ConnectionResetError:
                    break
                if not chunk:
                    break
        async with aiohttp.ClientSession(base_url=gw.http_url) as http, http.get("/api/v1/health") as health:
            assert health.status == 200
    finally:
        slow.close()


async def test_one_clients_many_streams_do_not_keep_another_out(gateway_process: StartGateway) -> None:
    gw = gateway_process(CONFIG + "\n[http]\nmax_streams = 8\nmax_streams_per_client = 4\n")
    port = port_of(gw)
    greedy = [await open_from("127.0.0.2", port) for _ in range(4)]
    try:
        assert [await first_line(reader) for reader, _ in greedy] == [200] * 4
        reader, writer = await open_from("127.0.0.2", port)
        greedy.append((reader, writer))
        status, error = await error_of(reader)
        assert status == 429
        assert error["code"] == "RESOURCE_EXHAUSTED"
        assert "http.max_streams_per_client" in error["message"] and "127.0.0.2" in error["message"]
        # Another client still gets its streams, up to its own share of the rest.
        other = [await open_from("127.0.0.3", port) for _ in range(4)]
        greedy.extend(other)
        assert [await first_line(reader) for reader, _ in other] == [200] * 4
        # Now every place is taken: a third client is told so, naming the total bound.
        reader, writer = await open_from("127.0.0.4", port)
        greedy.append((reader, writer))
        status, error = await error_of(reader)
        assert status == 503 and "http.max_streams" in error["message"], error
        # A stream closed frees its client's place.
        greedy[0][1].close()

        async def reopen() -> int:
            r, w = await open_from("127.0.0.2", port)
            greedy.append((r, w))
            return await first_line(r)

        await eventually(reopen, lambda status: status == 200)
    finally:
        for _, writer in greedy:
            with contextlib.suppress(Exception):
                writer.close()


async def test_a_thousand_idle_streams_from_several_clients_are_served(gateway_process: StartGateway) -> None:
    """The defaults serve 1,000 idle event streams from 20 clients (50 each) and everyone else goes on."""
    gw = gateway_process(CONFIG)
    port = port_of(gw)
    sources = [f"127.0.0.{10 + n}" for n in range(20)]
    connections: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []
    try:
        for n in range(1000):
            connections.append(await open_from(sources[n % len(sources)], port))
        statuses = await asyncio.gather(*(first_line(reader) for reader, _ in connections))
        assert statuses == [200] * 1000
        async with (
            aiohttp.ClientSession(base_url=gw.http_url) as http,
            AsyncClient(gw.address, timeout=10) as client,
        ):
            await client.set("board", "note", "a thousand listen")
            async with http.get("/api/v1/services/board/properties/note") as got:
                assert (await got.json())["value"] == "a thousand listen"
            assert await client.get("board", "note") == "a thousand listen"
            await eventually(lambda: read_some(connections[-1][0]), lambda text: b"a thousand listen" in text)
    finally:
        for _, writer in connections:
            with contextlib.suppress(Exception):
                writer.close()
