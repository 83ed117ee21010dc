"""The OPC UA peer's load: part (s)'s four patterns through asyncua's client, in this process's loop.

* Get one at a time, and 8 in flight: Read of the variable's value on one
  client connection (one secure channel and session), as the gRPC parts
  make unary Gets on one channel; asyncua pipelines concurrent Reads.
* Fan-out: ``subscribers`` monitored items on the variable, spread over
  ``channels`` client connections as the gRPC Listen streams are (25 a
  connection). Each connection has one subscription with publishing interval
  0 (the server publishes at each change rather than on a timer) holding its
  monitored items, which is how an OPC UA client watches values: one
  subscription per session, one monitored item per value watched. So one
  Write reaches each connection as one Publish response carrying a
  notification for each of its items. Queue size 10,000 (asyncua's cap) so
  that a slow reader loses nothing. The setter Writes on the first
  connection, one Write at a time, as fast as they are answered
  (``one-by-one``), or at ``set_rate`` a second (``paced``).

Every latency is client side, from the Write's start (its value is
``perf_counter_ns``) to the notification's arrival in the handler.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from bench.listen import ListenResult
from bench.peer_measure import (
    SYNC_TIMEOUT,
    SYNC_VALUE,
    Fanout,
    PeerRound,
    PeerSizes,
    Receiver,
    drive_calls,
    measure_patterns,
    poll_until,
)
from bench.peer_opcua_server import ENDPOINT_PATH, NAMESPACE, VALUE_NODE
from bench.servers import ServerProcess

#: A Read or Write slower than this counts as an error, seconds.
CALL_TIMEOUT = 10.0
#: Notifications a monitored item may queue on the server (asyncua's own cap).
QUEUE_SIZE = 10_000


class _Handler:
    """A subscription's notifications, each handed to the receiver of its monitored item."""

    def __init__(self, receivers: Sequence[Receiver]) -> None:
        self._free = list(receivers)
        self._by_handle: dict[int, Receiver] = {}

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        handle = data.monitored_item.ClientHandle
        receiver = self._by_handle.get(handle)
        if receiver is None:
            # Each item's first notification is the value it found (SYNC_VALUE): a receiver for each.
            receiver = self._by_handle[handle] = self._free.pop()
        receiver.note(val)


def _quiet() -> None:
    # asyncua warns of the session timeout it revised and of the subscription parameters it changed.
    logging.getLogger("asyncua").setLevel(logging.ERROR)


async def _fanout(server: ServerProcess, url: str, write: Any, fanout: Fanout) -> ListenResult:
    from asyncua import Client, ua

    receivers = fanout.receivers
    channels = fanout.result.channels
    await write(SYNC_VALUE)
    connected: list[Any] = []
    try:
        for number in range(channels):
            client = Client(url, timeout=CALL_TIMEOUT)
            await client.connect()
            connected.append(client)
            mine = receivers[number::channels]
            index = await client.get_namespace_index(NAMESPACE)
            subscription = await client.create_subscription(0, _Handler(mine))
            await subscription.subscribe_data_change(
                [client.get_node(ua.NodeId(VALUE_NODE, index))] * len(mine), queuesize=QUEUE_SIZE
            )
        if not await poll_until(lambda: fanout.synced() == len(receivers), SYNC_TIMEOUT):
            raise RuntimeError(f"{fanout.synced()} of {len(receivers)} monitored items had their first value")
        return await fanout.measure(server, write, (ua.UaError, TimeoutError))
    finally:
        for client in connected:
            await client.disconnect()


async def run_opcua(server: ServerProcess, sizes: PeerSizes) -> PeerRound:
    """Measure the OPC UA server ``server`` with the four patterns of part (s)."""
    from asyncua import Client, ua

    _quiet()
    url = f"opc.tcp://{server.address}{ENDPOINT_PATH}"
    async with Client(url, timeout=CALL_TIMEOUT) as client:
        node = client.get_node(ua.NodeId(VALUE_NODE, await client.get_namespace_index(NAMESPACE)))

        async def write(value: str) -> None:
            await node.write_value(ua.Variant(value, ua.VariantType.String))

        await write("0")

        async def drive(count: int, in_flight: int, deadline: float) -> tuple[list[int], int, bool]:
            return await drive_calls(node.read_value, count, in_flight, deadline, (ua.UaError, TimeoutError))

        return await measure_patterns(
            server,
            sizes,
            drive=drive,
            fan_out=lambda fanout: _fanout(server, url, write, fanout),
            system="opcua",
            client="asyncua Client: Read and Write; a subscription per connection (publishing interval 0)",
        )
