"""The device server as a real process, spoken to with raw TCP sockets and a real pty."""

from __future__ import annotations

import asyncio
import os
import re
import sys
from asyncio.subprocess import PIPE
from collections.abc import Mapping

from line_device_support import LineClient, device_process, pty_client, pty_pair, tcp_device
from support.fake_backend import DictBackend

from services.device import DeviceServer
from services.kernel.backend import NO_PARAMS
from services.kernel.line_protocol import BadLine, Frame, Get, LineReceiver, Ok, crc8, encode
from services.kernel.values import Value


async def test_a_whole_tcp_session() -> None:
    with tcp_device("--service", "sim-robot", "--name", "scout1", "--option", "tick_hz=50") as (host, port):
        c = await LineClient.tcp(host, port)
        assert await c.line() == "HELLO 1 name=scout1 type=mobile_robot push=1 maxline=1024"
        await c.send("get location")
        assert await c.line() == "OK (0 0 0 0 0 0)"
        await c.send("#1 GET location.x", "#2 GET speed")
        assert sorted(await c.lines(2)) == ["#1 OK 0", "#2 OK 0.5"]
        await c.send("SET speed 2")
        assert await c.line() == "OK 2"
        await c.send("#7 LISTEN location.x")
        assert await c.line() == "#7 OK 0"
        await c.send("SET behaviors.moveto <marker><location>(1 0)</location></marker>")
        reply, _ = await c.until("OK")
        assert reply == "OK"
        event, _ = await c.until("EVENT location.x")
        assert float(event.split()[2]) > 0
        await c.send("#8 GET nosuch", "SET location.x abc", "FROB x", "#9 PING 42")
        replies = await c.replies(4)
        assert any(r.startswith("#8 ERR 5 ") for r in replies), replies
        assert any(r.startswith("ERR 9 ") for r in replies), replies  # location is read-only
        assert "ERR 12 unknown word 'FROB'" in replies
        assert "#9 PONG 42" in replies
        await c.send("UNLISTEN location.x")
        reply, _ = await c.until("OK")
        assert reply == "OK"
        await c.close()


async def test_bad_lines_get_errors_and_the_connection_lives_on() -> None:
    with tcp_device("--service", "sim-sensor") as (host, port):
        c = await LineClient.tcp(host, port)
        await c.line()
        await c.send(b"\x00\xff\xfe garbage\n", b"#5 SET x " + b"y" * 3000 + b"\n", b"#6 SET a b\\q\n")
        await c.send(encode(Get("location", tag="7"))[:-1] + b" junk\n", b"$#8 GET location*00\n")
        replies = await c.lines(5)
        assert replies[0].startswith("ERR 3 line is not valid UTF-8")
        assert replies[1].startswith("#5 ERR 8 line too long")
        assert replies[2].startswith("#6 ERR 3 bad escape")
        assert replies[3].startswith("#7 ERR 3 unexpected text")
        # The reply to a $-line carries a checksum, the ERR of a damaged one too (docs/device-spec.md §6.4).
        assert replies[4].startswith("$ERR 15 checksum mismatch")
        assert int(replies[4][-2:], 16) == crc8(replies[4][1:-3].encode())
        await c.send(f"$#9 GET location*{crc8(b'#9 GET location'):02X}")
        reply = await c.line()
        assert re.fullmatch(r"\$#9 OK \(.*\)\*[0-9A-F]{2}", reply), reply
        await c.close()


async def test_several_clients_at_once() -> None:
    with tcp_device("--service", "sim-robot") as (host, port):
        clients = [await LineClient.tcp(host, port) for _ in range(5)]
        for c in clients:
            await c.line()
        for i, c in enumerate(clients):
            await c.send(f"#{i} GET speed")
        assert [await c.line() for c in clients] == [f"#{i} OK 0.5" for i in range(5)]
        for c in clients:
            await c.close()


async def test_device_without_push_refuses_listen() -> None:
    with tcp_device("--service", "sim-sensor", "--no-push") as (host, port):
        c = await LineClient.tcp(host, port)
        assert "push=0" in await c.line()
        await c.send("#1 LISTEN data")
        assert (await c.line()).startswith("#1 ERR 12 ")
        await c.close()


async def test_serial_device_on_a_pty() -> None:
    with (
        pty_pair() as (master, path),
        device_process("--service", "sim-robot", "--name", "tty1", "--serial", path) as (
            _,
            first,
        ),
    ):
        assert first == f"serving on {path}"
        c = await pty_client(master)
        # The greeting sent when the port opened may have been lost to the pty; ask again.
        await c.send("#h HELLO")
        hello, _ = await c.until("#h HELLO")
        assert "name=tty1" in hello and "push=1" in hello
        await c.send("#1 GET speed", "garbage line", "#2 get location.y")
        assert sorted(await c.lines(3)) == ["#1 OK 0.5", "#2 OK 0", "ERR 12 unknown word 'garbage'"]
        await c.close()


async def test_device_on_its_own_pty_ends_with_its_stdin() -> None:
    # What the gateway runs for a ``[[devices]]`` entry with ``serial = "pty"``.
    args = [
        "--service",
        "sim-robot",
        "--name",
        "tty2",
        "--option",
        "speed=0.25",
        "--pty",
        "--exit-with-parent",
    ]
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "services.device", *args, stdin=PIPE, stdout=PIPE
    )
    try:
        assert proc.stdin is not None and proc.stdout is not None
        first = await asyncio.wait_for(proc.stdout.readline(), 10)
        match = re.fullmatch(r"serial port (/dev/pts/\d+)", first.decode().strip())
        assert match, f"the device did not say which serial port to open: {first!r}"
        fd = os.open(match.group(1), os.O_RDWR | os.O_NOCTTY)
        try:
            c = await pty_client(fd)
            await c.send("#h HELLO")
            hello, _ = await c.until("#h HELLO")
            assert "name=tty2" in hello and "type=mobile_robot" in hello
            for request, reply in [
                ("GET speed", "OK 0.25"),
                ("SET speed 0.5", "OK 0.5"),
                ("GET speed", "OK 0.5"),
            ]:
                await c.send(request)
                assert await c.line() == reply
            await c.close()
        finally:
            os.close(fd)
        proc.stdin.close()  # the parent is gone: the device stops by itself, cleanly
        assert await asyncio.wait_for(proc.wait(), 10) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_slow_reader_gets_conflated_events_and_the_latest_value() -> None:
    backend = DictBackend({"n": "0"}, type="counter")
    server = DeviceServer(backend, name="counter")
    host, port = await server.serve_tcp("127.0.0.1", 0)
    try:
        c = await LineClient.tcp(host, port)
        await c.line()
        await c.send("LISTEN n")
        assert await c.line() == "OK 0"
        emitted = 5000
        pad = "x" * 900
        for i in range(1, emitted + 1):
            backend.put("n", f"{i} {pad}")
            if i % 500 == 0:
                await asyncio.sleep(0)  # let the writer run; the reader (this test) does not read yet
        received = []
        while True:
            line = await c.line()
            received.append(line)
            if line.startswith(f"EVENT n {emitted} "):
                break
        assert len(received) < emitted
        await c.close()
    finally:
        await server.aclose()


async def test_a_client_that_does_not_read_long_binary_replies_stops_the_device_reading() -> None:
    # 300 GETs of a 1 MB binary value in one write, and nothing read: the device stops taking
    # requests once about 8 MiB of replies wait (not 300 × 1.3 MB of base64 in memory), and
    # answers every one of them, byte for byte, once the client reads.
    value = os.urandom(1_000_000)
    asked = 0

    class Camera(DictBackend):
        async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
            nonlocal asked
            asked += 1
            return value

    server = DeviceServer(Camera({"frame": ""}), name="camera", max_line=2 * 1024 * 1024)
    host, port = await server.serve_tcp("127.0.0.1", 0)
    try:
        reader, writer = await asyncio.open_connection(host, port, limit=4 * 1024 * 1024)
        await reader.readline()  # the greeting
        writer.write(b"".join(encode(Get("frame", tag=str(i))) for i in range(300)))
        await writer.drain()
        await asyncio.sleep(1.0)  # the client reads nothing meanwhile
        # Answered meanwhile: the 32 requests running at once, ~8 MiB waiting in the outbox and as
        # much in the writer's hands, and what the sockets' and the client's buffers took (~60).
        held_back = asked
        assert held_back < 120, f"{held_back} of 300 GETs answered into a client that does not read"
        receiver = LineReceiver(max_line=2 * 1024 * 1024)
        replies: list[Frame | BadLine] = []
        async with asyncio.timeout(60):
            while len(replies) < 300:
                replies += receiver.receive_data(await reader.read(1 << 20))
        assert all(isinstance(r, Ok) and r.value == value for r in replies)
        assert sorted(int(r.tag or "-1") for r in replies if isinstance(r, Ok)) == list(range(300))
        writer.close()
    finally:
        await server.aclose()
