"""A Session listen's buffer: a slow reader gets the latest value per property, what it missed counted."""

from __future__ import annotations

import asyncio

from clients.aio import HEARTBEAT, SYNC, Event
from clients.aio.listen_buffer import ListenBuffer
from clients.errors import Unavailable
from protos.propertyservice.v1 import property_service_pb2 as pb


def _response(
    *events: tuple[str, str, int, bool], sync: bool = False, heartbeat: bool = False
) -> pb.ListenResponse:
    return pb.ListenResponse(
        events=[pb.Event(service="s", property=p, value=v, conflated=c, gap=g) for p, v, c, g in events],
        sync=sync,
        heartbeat=heartbeat,
    )


def _values(items: list[object]) -> list[object]:
    """Each event as its value, each marker as itself."""
    return [item.value if isinstance(item, Event) else item for item in items]


async def _drain(buffer: ListenBuffer) -> list[object]:
    items: list[object] = []
    while (item := await buffer.next()) is not None:
        items.append(item)
    return items


async def test_a_slow_reader_gets_the_latest_value_with_every_missed_value_counted() -> None:
    buffer = ListenBuffer(marks=False)
    buffer.add(_response(("a", "1", 0, False), ("b", "x", 0, False)))
    buffer.add(_response(("a", "2", 3, False)))  # the gateway already conflated 3 values before "2"
    buffer.add(_response(("a", "3", 1, True)))
    buffer.finish(None)
    items = await _drain(buffer)
    assert [(e.property, e.value, e.conflated, e.gap) for e in items if isinstance(e, Event)] == [
        ("a", "3", 0 + 3 + 1 + 2, True),  # the gateway's counts, plus the two values replaced here
        ("b", "x", 0, False),
    ]


async def test_markers_only_when_asked_and_not_repeated() -> None:
    quiet = ListenBuffer(marks=False)
    quiet.add(_response(("a", "1", 0, False), sync=True, heartbeat=True))
    quiet.finish(None)
    assert _values(await _drain(quiet)) == ["1"]

    marked = ListenBuffer(marks=True)
    marked.add(_response(("a", "1", 0, False), sync=True))
    marked.add(_response(heartbeat=True))
    marked.add(_response(heartbeat=True))
    marked.finish(None)
    items = await _drain(marked)
    assert _values(items) == ["1", SYNC, HEARTBEAT]


async def test_the_reader_waits_for_an_item_and_learns_why_the_stream_ended() -> None:
    buffer = ListenBuffer(marks=False)
    reader = asyncio.ensure_future(buffer.next())
    await asyncio.sleep(0)
    assert not reader.done()
    buffer.add(_response(("a", "1", 0, False)))
    first = await asyncio.wait_for(reader, 1)
    assert isinstance(first, Event)
    assert first.value == "1"
    error = Unavailable(None, "the gateway ended the session")
    buffer.finish(error)
    assert await buffer.next() is None
    assert buffer.done
    assert buffer.error is error
