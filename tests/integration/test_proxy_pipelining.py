"""Pipelining on the one connection of the TCP proxy, on real sockets.

Replies in any order answer their own requests; the device's window holds
while they do; a device that drops mid-pipeline fails exactly the requests it
left unanswered; the requests of one loop turn reach the device in one read
(and a Session message of Gets through a real gateway process comes back as
one message); each request expires at its own deadline under the connection's
one timer, whose heap stays bounded. A caller that knows its batch is complete
sends it without waiting for the turn's end, and a reply reaches a ``then``
receiver in the reader, before the future's done-callbacks run.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import grpc
import pytest
from line_device_support import started_tcp_proxy
from support.session_stream import replies_until
from support.waiting import WAIT, eventually

from gateway.proxies import TcpProxy
from gateway.proxies.connection import LineConnection
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.errors import Code, PropertyError
from services.kernel.line_protocol import Get, Ok

GREETING = "HELLO 1 name=fake type=thing push=1"
FAST = {"timeout": 5.0, "connect_timeout": 5.0, "backoff_initial": 0.05, "backoff_max": 0.3}


class DeviceLink:
    """The device's end of one connection: what each read brought, and replies written as told."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, greeting: str) -> None:
        self.reader = reader
        self.writer = writer
        self.greeting = greeting
        #: The bytes of each read, in order.
        self.chunks: list[bytes] = []
        self._partial = b""

    async def requests(self, at_least: int = 1) -> list[tuple[str, str]]:
        """Read until ``at_least`` requests are in; return each as (tag, request), in arrival order.

        HELLO and PING are answered here and not returned. Raises ConnectionError at end of stream.
        """
        got: list[tuple[str, str]] = []
        while len(got) < at_least:
            data = await self.reader.read(65536)
            if not data:
                raise ConnectionError("the proxy closed the connection")
            self.chunks.append(data)
            *lines, self._partial = (self._partial + data).split(b"\n")
            for raw in lines:
                head, _, request = raw.decode().partition(" ")
                if raw.startswith(b"HELLO"):
                    self.writer.write(self.greeting.encode() + b"\n")
                elif request.startswith("PING"):
                    self.writer.write(f"{head} PONG\n".encode())
                else:
                    got.append((head.removeprefix("#"), request))
        return got

    def answer(self, replies: list[tuple[str, str]]) -> None:
        """Write the replies, each ``(tag, "OK value")`` or ``(tag, "ERR ...")``, in one write."""
        self.writer.write(b"".join(f"#{tag} {text}\n".encode() for tag, text in replies))


def path_of(request: str) -> str:
    return request.split()[1]


@asynccontextmanager
async def fake_device(
    serve: Callable[[DeviceLink], Awaitable[None]], greeting: str = GREETING
) -> AsyncIterator[tuple[str, list[DeviceLink]]]:
    """A device on a free port of 127.0.0.1 that greets, then runs ``serve`` per connection.

    It runs in a thread with an event loop of its own, as a device is a process of its own:
    it reads while the proxy writes, so what one read brings is what the proxy's writes made
    of it. Yields its ``tcp://`` URL and the links of the connections made so far.
    """
    links: list[DeviceLink] = []
    started: concurrent.futures.Future[tuple[asyncio.AbstractEventLoop, asyncio.Event, str]]
    started = concurrent.futures.Future()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        link = DeviceLink(reader, writer, greeting)
        links.append(link)
        writer.write(greeting.encode() + b"\n")
        try:
            await serve(link)
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def run() -> None:
        stop = asyncio.Event()
        try:
            server = await asyncio.start_server(handle, "127.0.0.1", 0)
        except OSError as exc:
            started.set_exception(exc)
            return
        host, port = server.sockets[0].getsockname()[:2]
        started.set_result((asyncio.get_running_loop(), stop, f"tcp://{host}:{port}"))
        async with server:
            await stop.wait()  # asyncio.run then cancels the connections' handlers

    thread = threading.Thread(target=asyncio.run, args=(run(),), name="fake device", daemon=True)
    thread.start()
    loop, stop, url = await asyncio.wait_for(asyncio.wrap_future(started), WAIT)
    try:
        yield url, links
    finally:
        loop.call_soon_threadsafe(stop.set)
        await asyncio.to_thread(thread.join, WAIT)
        assert not thread.is_alive(), "the fake device did not stop"


@asynccontextmanager
async def proxy_for(url: str, **options: object) -> AsyncIterator[TcpProxy]:
    async with started_tcp_proxy(url, {**FAST, **options}) as proxy:
        await proxy.wait_connected(WAIT)
        yield proxy


async def answer_each_read(
    link: DeviceLink, order: Callable[[list[tuple[str, str]]], list[tuple[str, str]]]
) -> None:
    """Answer what every read brought, in one write per read, in the order ``order`` puts it."""
    while True:
        got = await link.requests()
        link.answer([(tag, f"OK {path_of(request)}") for tag, request in order(got)])


def interleaved(got: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """Last first, then first, then the one before last, ...: no reply where its request was."""
    rest = list(got)
    out = []
    while rest:
        out.append(rest.pop())
        if rest:
            out.append(rest.pop(0))
    return out


async def test_replies_in_any_order_answer_their_own_requests() -> None:
    async with (
        fake_device(lambda link: answer_each_read(link, interleaved)) as (url, links),
        proxy_for(url) as proxy,
    ):
        paths = [f"p{i}" for i in range(12)]
        assert await asyncio.gather(*(proxy.get(path) for path in paths)) == paths
        # Once more, mixed with a Set that the device answers as a Get: each gets its own.
        again = await asyncio.gather(*(proxy.get(path) for path in reversed(paths)), proxy.set("p3", "x"))
        assert again == [*reversed(paths), "p3"]
    (link,) = links
    assert sum(chunk.count(b"\n") for chunk in link.chunks) == 25


async def test_the_requests_of_one_loop_turn_reach_the_device_in_one_read_and_one_write_answers_them() -> (
    None
):
    async def serve(link: DeviceLink) -> None:
        got = await link.requests(20)
        link.answer([(tag, f"OK {path_of(request)}") for tag, request in got])  # all in one write
        await answer_each_read(link, list)

    async with fake_device(serve) as (url, links), proxy_for(url) as proxy:
        paths = [f"p{i}" for i in range(20)]
        assert await asyncio.gather(*(proxy.get(path) for path in paths)) == paths
    (link,) = links
    first = link.chunks[0]
    assert first.count(b"\n") == 20, first  # one write of the 20 lines: one read at the device
    assert [path_of(line.decode().partition(" ")[2]) for line in first.splitlines()] == paths


@pytest.mark.parametrize("window", [1, 3])
async def test_the_device_window_holds_while_replies_come_in_any_order(window: int) -> None:
    most = 0

    async def serve(link: DeviceLink) -> None:
        nonlocal most
        while True:
            got = await link.requests()
            # Lines that come while it works count as unanswered too: a proxy over the window shows.
            await asyncio.sleep(0.01)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.001):
                    got += await link.requests()
            most = max(most, len(got))
            link.answer([(tag, f"OK {path_of(request)}") for tag, request in interleaved(got)])

    async with fake_device(serve, f"{GREETING} inflight={window}") as (url, _), proxy_for(url) as proxy:
        paths = [f"p{i}" for i in range(12)]
        assert await asyncio.gather(*(proxy.get(path) for path in paths)) == paths
    assert most == window  # as many as the device takes, never more


async def test_a_device_that_drops_mid_pipeline_fails_exactly_the_requests_it_left_unanswered() -> None:
    async def serve(link: DeviceLink) -> None:
        got = await link.requests(10)
        link.answer([(tag, f"OK {path_of(request)}") for tag, request in got[:4]])
        await link.writer.drain()
        # Hangs up with six requests unanswered (everything sent was read: a clean FIN, no RST).

    async with fake_device(serve) as (url, _), proxy_for(url, backoff_initial=5, backoff_max=5) as proxy:
        paths = [f"p{i}" for i in range(10)]
        results = await asyncio.gather(*(proxy.get(path) for path in paths), return_exceptions=True)
        assert results[:4] == paths[:4]
        for failed in results[4:]:
            assert isinstance(failed, PropertyError) and failed.code == Code.UNAVAILABLE, failed
            assert "closed the connection" in failed.message
        with pytest.raises(PropertyError) as later:
            await proxy.get("p0")
        assert later.value.code == Code.UNAVAILABLE


async def test_each_request_expires_at_its_own_deadline_under_the_connections_one_timer() -> None:
    async def serve(link: DeviceLink) -> None:
        while True:
            got = await link.requests()
            link.answer([(tag, "OK fine") for tag, request in got if "slow" not in request])

    async with fake_device(serve) as (url, _), proxy_for(url, timeout=1.5) as proxy:
        loop = asyncio.get_running_loop()
        started = loop.time()
        ended: dict[str, float] = {}
        calls: dict[str, asyncio.Future[object]] = {
            "long": asyncio.ensure_future(proxy.get("slow-long")),  # the proxy's timeout: 1.5 s
            "short": _started(proxy.start_get("slow-short", {}, 0.3)),
            "middle": _started(proxy.start_get("slow-middle", {}, 0.8)),
        }
        for name, call in calls.items():
            call.add_done_callback(lambda _, name=name: ended.setdefault(name, loop.time() - started))
        assert await proxy.get("quick") == "fine"  # answered while the three wait
        await asyncio.wait(calls.values(), timeout=WAIT)
        for call in calls.values():
            error = call.exception()
            assert isinstance(error, PropertyError) and error.code == Code.DEADLINE_EXCEEDED, error
        assert sorted(ended, key=ended.__getitem__) == ["short", "middle", "long"]
        assert ended["short"] >= 0.3 and ended["middle"] >= 0.8 and ended["long"] >= 1.5, ended
        assert await proxy.get("quick") == "fine"


def _started(future: asyncio.Future[object] | None) -> asyncio.Future[object]:
    assert future is not None, "the proxy had no room for a request"
    return future


async def test_the_deadlines_of_answered_requests_are_dropped_so_the_timer_holds_a_bounded_heap() -> None:
    async with fake_device(lambda link: answer_each_read(link, list)) as (url, _):
        host, port = url.removeprefix("tcp://").split(":")
        connection = LineConnection(label="device fake", on_event=lambda frame: None)
        await asyncio.get_running_loop().create_connection(lambda: connection, host, int(port))
        try:
            await asyncio.wait_for(connection.hello, WAIT)
            held = []
            for round_ in range(10):
                replies = await asyncio.gather(*(connection.request(Get(f"p{n}"), 30.0) for n in range(100)))
                assert [reply.value for reply in replies if isinstance(reply, Ok)] == [
                    f"p{n}" for n in range(100)
                ], round_
                held.append(connection.deadlines_held)
            # 1,000 answered requests, all with their deadline 30 s ahead: far fewer kept than that.
            assert max(held) <= 2 * 100 + 256 + 100, held
            assert connection.in_flight == (0, 0)
        finally:
            await connection.aclose()


async def test_a_session_message_of_gets_is_one_read_at_the_device_and_one_message_back(
    gateway_process,
) -> None:
    async with fake_device(lambda link: answer_each_read(link, interleaved)) as (url, links):
        gw = gateway_process(f'[[services]]\nname = "dev"\nurl = "{url}"\n')
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await eventually(
                lambda: stub.Get(pb.GetRequest(service="dev", property="p0"), timeout=5),
                retry_on=(grpc.aio.AioRpcError,),
                what="the gateway reaches the device",
            )
            (link,) = links
            reads_before = len(link.chunks)
            call = stub.Session()
            paths = [f"p{i}" for i in range(10)]
            await call.write(
                pb.SessionRequest(
                    requests=[
                        pb.Request(id=n + 1, get=pb.GetRequest(service="dev", property=path))
                        for n, path in enumerate(paths)
                    ]
                )
            )
            first = await asyncio.wait_for(call.read(), WAIT)
            replies = await replies_until(call, lambda got: len(got) + len(first.replies) >= 10)
            await call.done_writing()
            # Each Get is answered once: from the reply as read, not again from its future.
            extra: list[pb.Reply] = []
            while (message := await asyncio.wait_for(call.read(), WAIT)) is not grpc.aio.EOF:
                extra.extend(message.replies)
            assert extra == []
    answered = {reply.id: reply.get.value for reply in [*first.replies, *replies]}
    assert answered == {n + 1: path for n, path in enumerate(paths)}
    assert len(first.replies) == 10  # one read of the device's one write: one SessionResponse
    batch = link.chunks[reads_before:]
    assert len(batch) == 1 and batch[0].count(b"\n") == 10, batch


async def test_a_batch_known_complete_goes_out_at_once_in_one_write() -> None:
    async with (
        fake_device(lambda link: answer_each_read(link, list)) as (url, links),
        proxy_for(url) as proxy,
    ):
        (link,) = links
        before = len(link.chunks)
        paths = [f"p{i}" for i in range(5)]
        futures = [proxy.start_get(path, {}, WAIT) for path in paths]
        proxy.flush()
        # No turn of this loop from here on: the device, in a thread of its own, reads them anyway.
        deadline = time.monotonic() + WAIT
        while len(link.chunks) == before and time.monotonic() < deadline:
            time.sleep(0.005)  # noqa: ASYNC251 - blocking on purpose: no loop turn
        assert len(link.chunks) == before + 1, "the lines did not reach the device before the turn ended"
        assert link.chunks[before].count(b"\n") == 5, link.chunks[before]
        assert all(future is not None for future in futures)
        answers = await asyncio.gather(*(future for future in futures if future is not None))
        assert [answer.value for answer in answers] == paths
        await asyncio.sleep(0.05)  # the turn's own flush has run since, and sent nothing again
    assert sum(chunk.count(b"\n") for chunk in link.chunks[before:]) == 5


async def answer_missing_with_an_error(link: DeviceLink) -> None:
    while True:
        got = await link.requests()
        link.answer(
            [
                (tag, "ERR 5 no such property" if path_of(request) == "missing" else f"OK {path_of(request)}")
                for tag, request in got
            ]
        )


async def test_a_reply_reaches_then_in_the_reader_before_the_future_is_done(caplog) -> None:
    async with fake_device(answer_missing_with_an_error) as (url, _), proxy_for(url) as proxy:
        seen: list[tuple[str, bool]] = []
        futures: list[asyncio.Future] = []

        def then(answer) -> None:
            seen.append((answer.value, futures[0].done()))

        future = proxy.start_get("p1", {}, WAIT, then)
        assert future is not None
        futures.append(future)
        assert (await future).value == "p1"
        assert seen == [("p1", False)]

        # An error reply comes only through the future.
        failed = proxy.start_get("missing", {}, WAIT, then)
        assert failed is not None
        with pytest.raises(PropertyError) as raised:
            await failed
        assert raised.value.code == Code.NOT_FOUND
        assert seen == [("p1", False)]

        # A receiver that fails is logged; the future is resolved all the same.
        def broken(_answer) -> None:
            raise RuntimeError("the receiver broke")

        with caplog.at_level(logging.ERROR, logger="gateway.proxies.connection"):
            resolved = proxy.start_get("p2", {}, WAIT, broken)
            assert resolved is not None
            assert (await resolved).value == "p2"
        assert any("receiver of the reply" in record.getMessage() for record in caplog.records)
