"""Small line-protocol devices (docs/device-spec.md, 1.1 on) against the gateway's proxies and line listener.

Each device is played by the test on a real TCP socket or a real pty
(:mod:`scripted_device`): it restarts mid-session, drops a property and gets
it back, says how much it can take in flight, greets in a way the gateway
must refuse, sends requests of its own. The gateway side is the real thing:
the proxies in-process on those sockets, or a whole in-process gateway whose
clients use gRPC.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import grpc
import pytest
from line_device_support import LineClient, tcp_device
from scripted_device import ScriptedDevice, pty_scripted, tcp_scripted
from support.waiting import eventually, wait_until

from clients.aio import AsyncClient
from clients.errors import PropertyServiceError
from gateway.app import Gateway
from gateway.config import parse_config
from gateway.proxies import LineProxy, SerialProxy, TcpProxy, open_serial_backend, open_tcp_backend
from services.kernel.backend import Change
from services.kernel.errors import Code, PropertyError
from services.kernel.line_protocol import crc8

FAST = {
    "timeout": 2.0,
    "connect_timeout": 2.0,
    "backoff_initial": 0.05,
    "backoff_max": 0.3,
    "poll_interval": 0.05,
}
WAIT = 10.0
THERM = "HELLO 1 name=therm type=sensor push=1 maxline=64"


@asynccontextmanager
async def proxy_for(url: str, **options: object) -> AsyncIterator[LineProxy]:
    opened = (
        open_serial_backend("dev", f"serial://{url}", {**FAST, **options})
        if url.startswith("/")
        else open_tcp_backend("dev", url, {**FAST, **options})
    )
    assert isinstance(opened, TcpProxy | SerialProxy)
    await opened.start()
    try:
        yield opened
    finally:
        await opened.aclose()


async def next_change(queue: asyncio.Queue[Change]) -> Change:
    return await asyncio.wait_for(queue.get(), WAIT)


def checked(line: str) -> bytes:
    body = line.encode()
    return b"$" + body + b"*%02X\n" % crc8(body)


def checksum_ok(line: str) -> bool:
    return line.startswith("$") and line[-3] == "*" and int(line[-2:], 16) == crc8(line[1:-3].encode())


# -- a restart in the middle of a session --------------------------------------


@asynccontextmanager
async def scripted_on(transport: str, device: ScriptedDevice) -> AsyncIterator[str]:
    """``device`` on a real TCP socket, or on a real pty (there it greets when asked or after a reset)."""
    if transport == "tcp":
        async with tcp_scripted(device) as url:
            yield url
    else:
        device.greet_first = False
        async with pty_scripted(device) as path:
            yield path


@pytest.mark.parametrize("transport", ["tcp", "serial"])
async def test_a_device_that_restarts_mid_session_gets_its_listens_back_and_the_next_value_is_a_gap(
    transport: str,
) -> None:
    device = ScriptedDevice(f"{THERM} inflight=4", {"temp": "21.5", "rate": "1", "slow": "x"})
    async with scripted_on(transport, device) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(WAIT)
        temps: asyncio.Queue[Change] = asyncio.Queue()
        rates: asyncio.Queue[Change] = asyncio.Queue()
        await proxy.listen("temp", temps.put_nowait)
        await proxy.listen("rate", rates.put_nowait)
        device.change("temp", "21.6")
        assert (await next_change(temps)).value == "21.6"

        device.delay = 0.5  # a request on its way when the device resets is lost with its RAM
        lost = asyncio.ensure_future(proxy.get("slow"))
        await wait_until(
            lambda: bool(device.seen("GET slow")), within=WAIT, what="the GET reached the device"
        )
        device.delay = 0.0
        device.props["temp"] = "21.7"  # the value moved on while it rebooted: nobody heard it
        device.restart()  # its subscriptions are gone with its RAM; it greets unasked
        with pytest.raises(PropertyError) as info:
            await asyncio.wait_for(lost, WAIT)
        assert info.value.code == Code.UNAVAILABLE and "restarted" in info.value.message
        await wait_until(
            lambda: device.subscribed == {"temp", "rate"}, within=WAIT, what="LISTENs sent again"
        )
        # The value it has now comes marked as a gap: values may have been missed.
        first = await next_change(temps)
        assert (first.value, first.gap) == ("21.7", True)
        assert (await next_change(rates)).gap
        device.change("temp", "21.8")
        after = await next_change(temps)
        assert (after.value, after.gap) == ("21.8", False)
        assert device.connections == 1  # the same connection all along
        assert await proxy.get("rate") == "1"


async def test_a_boot_greeting_and_the_answer_to_hello_are_not_a_restart() -> None:
    # A serial device greets when it boots and again when the gateway, having opened the
    # port, asks with HELLO. When the boot greeting comes first, the gateway is connected
    # and sends requests before the answer to its HELLO arrives: that answer must not
    # fail them as if the device had restarted.
    device = ScriptedDevice(f"{THERM} inflight=4", {"temp": "21.5"}, delay=0.5, greet_first=False)
    async with pty_scripted(device) as path, proxy_for(path) as proxy:
        await wait_until(lambda: bool(device.seen("HELLO")), within=WAIT, what="the gateway's HELLO")
        device.send(device.greeting)  # it booted just now; HELLO is answered 0.5 s later
        await proxy.wait_connected(WAIT)
        assert await proxy.get("temp") == "21.5"  # sent before the answer to HELLO arrives
        assert len(device.seen("GET temp")) == 1
        assert await proxy.get("temp") == "21.5"


# -- a property that goes and comes back ---------------------------------------


def one_device_gateway(url: str, **options: object) -> Gateway:
    return Gateway(
        parse_config(
            {
                "gateway": {"listen": "127.0.0.1:0", "line_listen": "127.0.0.1:0"},
                "services": [{"name": "therm", "url": url, "options": {**FAST, **options}}],
            }
        )
    )


async def test_a_grpc_listen_hears_removed_then_the_value_again_when_the_property_comes_back() -> None:
    device = ScriptedDevice(THERM, {"temp": "21.5"})
    async with (
        tcp_scripted(device) as url,
        one_device_gateway(url) as gw,
        AsyncClient(gw.address, timeout=5) as client,
    ):
        events = client.listen("therm", "temp")
        try:
            assert (await asyncio.wait_for(anext(events), WAIT)).value == "21.5"
            device.remove("temp")
            gone = await asyncio.wait_for(anext(events), WAIT)
            assert gone.removed
            device.props["temp"] = "30"  # plugged in again: nothing announces it (docs/device-spec.md §3.5)
            back = await asyncio.wait_for(anext(events), WAIT)
            assert (back.value, back.removed) == ("30", False)
            device.change("temp", "31")
            assert (await asyncio.wait_for(anext(events), WAIT)).value == "31"
        finally:
            await events.aclose()


# -- no traffic nobody asked for -----------------------------------------------


async def test_a_listen_costs_one_listen_line_and_location_is_listened_to_only_on_demand() -> None:
    device = ScriptedDevice(
        THERM,
        {"temp": "21.5", "rate": "1", "location": "(2 3 0 0 0 0)", "properties": "(temp rate location)"},
    )
    async with (
        tcp_scripted(device) as url,
        one_device_gateway(url) as gw,
        AsyncClient(gw.address, timeout=5) as client,
    ):
        events = client.listen("therm", "temp")
        try:
            assert (await asyncio.wait_for(anext(events), WAIT)).value == "21.5"
            assert await client.set("therm", "rate", "2") == "2"
            # Between the LISTEN and the SET that followed it, no GET of the same path.
            listen_at = device.lines.index(next(x for x in device.lines if x.endswith("LISTEN temp")))
            set_at = device.lines.index(next(x for x in device.lines if x.endswith("SET rate 2")))
            assert not [x for x in device.lines[listen_at:set_at] if x.endswith("GET temp")]
            assert device.seen("LISTEN location") == []  # nobody asked where it is
            assert device.seen("GET location") == []

            found = await client.get_names("registry", "find", near="(2 3)", radius="1")
            assert found == ["therm"]  # asked now: the registry follows it from here on
            assert len(device.seen("LISTEN location")) == 1
            assert await client.set("therm", "rate", "3") == "3"
            assert device.seen("GET location") == []  # the LISTEN's OK carried the value
        finally:
            await events.aclose()


# -- flow control ---------------------------------------------------------------


async def test_a_device_that_says_inflight_1_never_has_two_requests_unanswered() -> None:
    device = ScriptedDevice(f"{THERM} inflight=1", {"a": "1", "b": "2", "c": "3"}, delay=0.02)
    async with tcp_scripted(device) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(WAIT)
        values = await asyncio.gather(*(proxy.get(p) for p in "abcab"), proxy.set("a", "9"))
        assert values == ["1", "2", "3", "1", "2", "9"]
        assert device.max_unanswered == 1


async def test_a_32_byte_receive_buffer_is_never_overrun_and_longer_lines_are_refused_before_sending() -> (
    None
):
    device = ScriptedDevice(
        "HELLO 1 name=avr type=sensor push=1 maxline=64 rxbuf=32",
        {"speed": "1.5", "heading": "0", "x": "1", "y": "2", "z": "3"},
        delay=0.02,
        rxbuf=32,
    )
    async with tcp_scripted(device) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(WAIT)
        paths = ["speed", "heading", "x", "y", "z"] * 3
        assert await asyncio.gather(*(proxy.get(p) for p in paths)) == [device.props[p] for p in paths]
        assert await proxy.set("speed", "1.25") == "1.25"
        assert not device.overrun and device.max_unanswered_bytes <= 32
        assert device.max_unanswered >= 2  # short lines still go two at a time: rxbuf is in bytes
        with pytest.raises(PropertyError) as info:
            await proxy.set("speed", "1" * 40)  # fits maxline=64, not the 32-byte buffer
        assert info.value.code == Code.RESOURCE_EXHAUSTED
        assert not [line for line in device.lines if "1111111111" in line]  # never sent


async def test_whether_a_request_fits_the_receive_buffer_does_not_depend_on_how_long_it_ran() -> None:
    """Tags are a hex counter of 1 to 8 digits: a request is measured with the longest, so one that
    is refused is refused from the first request on, and one that is taken is taken for ever."""
    device = ScriptedDevice(
        "HELLO 1 name=avr type=sensor push=1 maxline=64 rxbuf=32", {"speed": "1"}, rxbuf=32
    )
    async with tcp_scripted(device) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(WAIT)
        # "#ffffffff SET speed " is 20 bytes: 11 bytes of value and the LF fill the 32 exactly.
        assert await proxy.set("speed", "1" * 11) == "1" * 11
        with pytest.raises(PropertyError) as info:
            await proxy.set("speed", "1" * 12)  # under the tag "#2" 26 bytes: the counter must not decide
        assert info.value.code == Code.RESOURCE_EXHAUSTED
        assert "33 bytes with the longest tag, the device takes 32" in info.value.message
        assert not [line for line in device.lines if "1" * 12 in line]


async def test_a_serial_device_that_states_nothing_gets_one_request_at_a_time() -> None:
    device = ScriptedDevice(THERM, {"a": "1", "b": "2"}, delay=0.02, greet_first=False)
    async with pty_scripted(device) as path, proxy_for(path) as proxy:
        await proxy.wait_connected(WAIT)
        assert await asyncio.gather(*(proxy.get(p) for p in "ababab")) == list("121212")
        assert device.max_unanswered == 1


async def test_a_device_that_does_not_answer_ping_within_keepalive_timeout_is_dropped() -> None:
    device = ScriptedDevice(THERM, {"a": "1"}, answer_pings=False)
    # The call timeout is long; the keep-alive's own timeout decides (docs/line-protocol.md §9).
    async with (
        tcp_scripted(device) as url,
        proxy_for(url, timeout=60, keepalive=0.5, keepalive_timeout=0.5) as proxy,
    ):
        await proxy.wait_connected(WAIT)
        await wait_until(lambda: device.connections >= 2, within=WAIT, what="dropped and dialled again")
        assert device.seen("PING")


# -- refusals -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("greeting", "status", "cause", "line_start"),
    [
        (
            "HELLO 2 name=next type=sensor",
            grpc.StatusCode.FAILED_PRECONDITION,
            "line protocol version 2 is not supported",
            "ERR 9 line protocol version 2 is not supported",
        ),
        (
            "HELLO 1 name=tiny maxline=32",
            grpc.StatusCode.INVALID_ARGUMENT,
            "maxline=32",
            "ERR 3 bad greeting: maxline=32",
        ),
        (
            "HELLO 1 name=odd rxbuf=many",
            grpc.StatusCode.INVALID_ARGUMENT,
            "rxbuf=",
            "ERR 3 bad greeting: rxbuf=",
        ),
    ],
)
async def test_a_refused_greeting_is_an_err_line_to_the_device_and_a_clear_status_to_the_registration(
    greeting: str, status: grpc.StatusCode, cause: str, line_start: str
) -> None:
    device = ScriptedDevice(greeting, {"a": "1"})
    async with (
        tcp_scripted(device) as url,
        Gateway(parse_config({"gateway": {"listen": "127.0.0.1:0"}})) as gw,
        AsyncClient(gw.address, timeout=15) as client,
    ):
        with pytest.raises(PropertyServiceError) as info:
            await client.set("registry", "services.dev", url)
        assert info.value.code == status, info.value
        assert cause in info.value.message and "was refused" in info.value.message
        assert "not connected yet" not in info.value.message
        err = await asyncio.wait_for(device.replies.get(), WAIT)
        assert err.startswith(line_start), err


async def greet_as(address: str, greeting: bytes) -> list[str]:
    """Dial the line listener, send ``greeting``, and return every line until the gateway hangs up."""
    host, _, port = address.rpartition(":")
    client = await LineClient.tcp(host, int(port))
    try:
        await client.send(greeting)
        data = await asyncio.wait_for(client.reader.read(), WAIT)
    finally:
        await client.close()
    return data.decode().splitlines()


async def test_a_device_dialling_in_with_a_greeting_it_cannot_have_gets_an_err_line_at_once() -> None:
    config = parse_config({"gateway": {"listen": "127.0.0.1:0", "line_listen": "127.0.0.1:0"}})
    async with Gateway(config) as gw:
        lines = await greet_as(gw.line_address, b"HELLO 2 name=future type=sensor push=1\n")
        assert lines[0].startswith("HELLO 1 name=gateway")
        assert lines[1:] == [
            "ERR 9 line protocol version 2 is not supported; this gateway speaks version 1 (1.3)"
        ]
        lines = await greet_as(gw.line_address, checked("HELLO 1 name=tiny maxline=32"))
        (err,) = lines[1:]
        assert checksum_ok(err) and err[1:].startswith("ERR 3 bad greeting: maxline=32")
        assert "future" not in gw.router and "tiny" not in gw.router


# -- checksums mirrored, requests on a proxy connection answered ----------------


async def test_the_line_listener_mirrors_checksums_even_on_a_damaged_line() -> None:
    config = parse_config({"gateway": {"listen": "127.0.0.1:0", "line_listen": "127.0.0.1:0"}})
    async with Gateway(config) as gw:
        host, _, port = gw.line_address.rpartition(":")
        line = await LineClient.tcp(host, int(port))
        try:
            assert (await line.line()).startswith("HELLO 1 name=gateway")
            await line.send(b"$#1 GET registry.services.registry*00\n")  # damaged
            damaged = await line.line()
            assert checksum_ok(damaged) and damaged[1:].startswith("ERR 15 checksum mismatch")
            await line.send(b"HELLO\n", checked("#2 GET registry.services.registry.state"))
            assert (await line.line()).startswith("HELLO 1 ")  # a plain HELLO: a plain greeting
            reply = await line.line()
            assert checksum_ok(reply) and reply[1:-3] == "#2 OK up"
        finally:
            await line.close()


async def test_requests_a_device_sends_on_a_proxy_connection_are_answered() -> None:
    device = ScriptedDevice(THERM, {"a": "1"})
    async with tcp_scripted(device) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(WAIT)
        device.send("#q GET registry.services")
        device.send("#r SET a 2", checksum=True)
        device.send("#p PING up?")
        replies = [await asyncio.wait_for(device.replies.get(), WAIT) for _ in range(3)]
        assert replies[0].startswith("#q ERR 12 not served: the gateway is the client here")
        assert checksum_ok(replies[1]) and replies[1][1:].startswith("#r ERR 12 ")
        assert replies[2] in ("#p PONG up?", f"${'#p PONG up?'}*{crc8(b'#p PONG up?'):02X}")
        assert await proxy.get("a") == "1"  # nothing else was disturbed


async def test_a_device_that_dialled_in_and_hung_up_is_waited_for_not_reconnected(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = parse_config({"gateway": {"listen": "127.0.0.1:0", "line_listen": "127.0.0.1:0"}})
    caplog.set_level(logging.INFO)
    async with Gateway(config) as gw, AsyncClient(gw.address, timeout=5) as client:
        host, _, port = gw.line_address.rpartition(":")
        line = await LineClient.tcp(host, int(port))
        await line.line()
        await line.send("HELLO 1 name=roamer type=sensor push=0")
        await eventually(lambda: client.get_names("registry", "services"), lambda n: "roamer" in n)
        await line.close()
        await wait_until(lambda: "waiting for it to dial in again" in caplog.text, within=WAIT)
        assert not [
            r for r in caplog.records if "roamer" in r.getMessage() and "reconnecting" in r.getMessage()
        ]


# -- the Python device side speaks 1.1 -----------------------------------------


async def test_the_python_device_states_its_flow_control_and_mirrors_checksums() -> None:
    with tcp_device("--service", "sim-robot", "--name", "bot", "--inflight", "1", "--rxbuf", "48") as (
        host,
        port,
    ):
        raw = await LineClient.tcp(host, port)
        try:
            greeting = await raw.line()
            assert greeting.startswith("HELLO 1 name=bot ") and greeting.endswith("inflight=1 rxbuf=48")
            await raw.send(b"$#1 GET speed*00\n")  # damaged: the ERR is untagged, and checksummed
            damaged = await raw.line()
            assert checksum_ok(damaged) and damaged[1:].startswith("ERR 15 checksum mismatch")
            await raw.send(b"HELLO\n", b"  GET speed\n")  # a plain HELLO, a line with leading spaces
            assert await raw.replies(2) == [greeting, "OK 0.5"]  # plain: checksum mode never began
        finally:
            await raw.close()
        async with proxy_for(f"tcp://{host}:{port}") as proxy:
            await proxy.wait_connected(WAIT)
            assert proxy.hello is not None and (proxy.hello.inflight, proxy.hello.rxbuf) == (1, 48)
            assert await asyncio.gather(*(proxy.get("speed") for _ in range(5))) == ["0.5"] * 5
