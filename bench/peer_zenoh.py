"""The Zenoh peer's load: part (s)'s four patterns through zenoh's Python binding, as zenoh clients.

Every session here is a zenoh *client* connected to the peer under test only
(:func:`bench.peer_zenoh_server.loopback_config`: no scouting), so what it
sends and receives passes through that process.

* Get one at a time: a ``get`` of ``bench/value`` through a declared
  querier, answered by the peer's queryable, the binding's blocking form
  (iterating the replies until the query is finished), one after another in
  one thread.
* 8 in flight: the same ``get`` with a callback handler run on zenoh's own
  network thread (``indirect=False``), whose end of query resolves a future
  in this loop, 8 coroutines on one session, as the gRPC parts make 8 unary
  Gets on one channel. Each form is the binding's fastest for its pattern
  here: 8 threads of blocking gets convoy on the GIL, and a callback on a
  thread of its own (the binding's default) costs a thread switch a reply.
* Fan-out: ``subscribers`` subscribers on the key, spread over ``channels``
  client sessions as the gRPC Listen streams are over connections (25 a
  session); the peer sends each put once to each session, which hands it to
  its 25 subscribers' callbacks (a plain function: the binding's default
  runs it on a Python thread of the subscriber's own, which here delivered
  about 8 × the events/s of callbacks on the network thread). The setter, a session
  of its own, puts with congestion control *block* (nothing dropped), as fast
  as ``put`` returns (``one-by-one``) or at ``set_rate`` a second
  (``paced``). A put has no answer: unlike a gRPC Set or an OPC UA Write, the
  setter does not wait for the server between values.

Latencies are client side: from the call (or the put, whose value is
``perf_counter_ns``) to the reply or the sample in the callback.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from bench.listen import ListenResult
from bench.peer_measure import (
    SYNC_TIMEOUT,
    SYNC_VALUE,
    Fanout,
    PeerRound,
    PeerSizes,
    drive_blocking,
    drive_calls,
    measure_patterns,
    poll_until,
)
from bench.peer_zenoh_server import KEY, QUERY_TIMEOUT, loopback_config
from bench.servers import ServerProcess

#: How often the setter repeats :data:`SYNC_VALUE` until every subscriber has it (declarations travel
#: to the peer on their own time, as a Listen's does before its ``sync``).
SYNC_REPEAT_S = 0.05


class _NoReply(RuntimeError):
    """A query finished without a value."""


def _network_thread_callback(on_reply: Any, on_end: Any) -> Any:
    """A handler whose callbacks run on zenoh's network thread (an unstable option), else the default."""
    import zenoh

    try:
        return zenoh.handlers.Callback(on_reply, on_end, indirect=False)
    except TypeError:
        return zenoh.handlers.Callback(on_reply, on_end)


async def _fanout(server: ServerProcess, endpoint: str, publisher: Any, fanout: Fanout) -> ListenResult:
    import zenoh

    receivers = fanout.receivers
    channels = fanout.result.channels
    sessions: list[Any] = []
    try:
        for _ in range(channels):
            sessions.append(zenoh.open(loopback_config("client", connect=[endpoint])))
        declared = [
            sessions[number % channels].declare_subscriber(
                KEY, lambda sample, receiver=receiver: receiver.note(sample.payload.to_string())
            )
            for number, receiver in enumerate(receivers)
        ]
        synced_by = time.monotonic() + SYNC_TIMEOUT
        while fanout.synced() < len(receivers):
            if time.monotonic() >= synced_by:
                raise RuntimeError(f"{fanout.synced()} of {len(receivers)} subscribers synced")
            publisher.put(SYNC_VALUE)
            await poll_until(lambda: fanout.synced() == len(receivers), SYNC_REPEAT_S)

        async def put(value: str) -> None:
            publisher.put(value)

        result = await fanout.measure(server, put, (zenoh.ZError,))
        for subscriber in declared:
            subscriber.undeclare()
        return result
    finally:
        for session in sessions:
            session.close()


async def run_zenoh(server: ServerProcess, sizes: PeerSizes) -> PeerRound:
    """Measure the zenoh peer ``server`` with the four patterns of part (s)."""
    import zenoh

    endpoint = f"tcp/{server.address}"
    session = zenoh.open(loopback_config("client", connect=[endpoint]))
    try:
        querier = session.declare_querier(KEY, timeout=QUERY_TIMEOUT)
        publisher = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        publisher.put("0")

        def get() -> str:
            for reply in querier.get():
                if reply.ok is not None:
                    value: str = reply.ok.payload.to_string()
                    return value
            raise _NoReply("a get of bench/value finished without a value")

        loop = asyncio.get_running_loop()

        async def get_soon() -> str:
            done: asyncio.Future[list[str]] = loop.create_future()
            values: list[str] = []

            def on_reply(reply: Any) -> None:
                if reply.ok is not None:
                    values.append(reply.ok.payload.to_string())

            def on_end() -> None:
                loop.call_soon_threadsafe(done.set_result, values)

            querier.get(handler=_network_thread_callback(on_reply, on_end))
            if not await done:
                raise _NoReply("a get of bench/value finished without a value")
            return values[0]

        async def drive(count: int, in_flight: int, deadline: float) -> tuple[list[int], int, bool]:
            errors = (zenoh.ZError, _NoReply)
            if in_flight == 1:
                return await drive_blocking(get, count, 1, deadline, errors)
            return await drive_calls(get_soon, count, in_flight, deadline, errors)

        def answers() -> bool:
            try:
                return get() == "0"
            except _NoReply:
                return False

        # Declarations reach the peer on their own time: put and ask until it answers what was put.
        synced_by = time.monotonic() + SYNC_TIMEOUT
        while not await asyncio.to_thread(answers):
            if time.monotonic() >= synced_by:
                raise RuntimeError("the zenoh peer never answered the value put to it")
            publisher.put("0")
            await asyncio.sleep(SYNC_REPEAT_S)
        measured = await measure_patterns(
            server,
            sizes,
            drive=drive,
            fan_out=lambda fanout: _fanout(server, endpoint, publisher, fanout),
            system="zenoh",
            client="zenoh client sessions: get through a querier, put with congestion control block",
        )
        querier.undeclare()
        publisher.undeclare()
    finally:
        session.close()
    return measured
