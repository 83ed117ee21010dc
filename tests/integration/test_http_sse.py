"""Listen as Server-Sent Events from a real gateway process: the order, resuming, heartbeats, errors.

Events come from the same listen hub as a gRPC Listen, so a Set through gRPC shows in an event
stream and the stream's sequence, snapshot and sync marker follow the gRPC contract.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import aiohttp
import pytest
from support.board import BOARD_TYPE
from support.gateway_process import GatewayProcess, StartGateway, start_gateway
from support.http_clients import grpc_client, http
from support.sse import SseReader

from clients import AsyncClient

__all__ = ["grpc_client", "http"]  # fixtures used by name

CONFIG = f"""
[http]
heartbeat = 0.3

[[services]]
name = "board"
type = "{BOARD_TYPE}"
"""

EVENTS = "/api/v1/events"


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_gateway(tmp_path_factory.mktemp("sse"), CONFIG)
    yield gw
    gw.stop()


async def test_current_values_then_sync_then_changes(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    await grpc_client.set("board", "note", "before")
    params = [("sel", "board/note"), ("sel", "board/level")]
    async with http.get(EVENTS, params=params) as response:
        assert response.status == 200
        assert response.headers["Content-Type"] == "text/event-stream; charset=utf-8"
        assert response.headers["Cache-Control"] == "no-cache"
        events = SseReader(response)
        snapshot = await events.values_until_sync()
        assert {m.data["path"]: m.data["value"] for m in snapshot} == {
            "note": "before",
            "level": await grpc_client.get("board", "level"),
        }
        assert all(m.data["service"] == "board" and not m.data["gap"] for m in snapshot)
        await grpc_client.set("board", "note", "after")
        change = await events.until("value")
        assert (change.data["path"], change.data["value"], change.data["gap"]) == ("note", "after", False)
        assert change.data["removed"] is False and change.data["time"] > 1.6e9
        ids = [int(m.id or 0) for m in [*snapshot, change]]
        assert ids == sorted(ids) and len(set(ids)) == len(ids) and ids[0] >= 1


async def test_a_set_over_http_reaches_a_grpc_listen(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    stream = grpc_client.listen("board", "lit", updates_only=True)
    first = asyncio.ensure_future(anext(stream))
    try:
        await asyncio.sleep(0.2)  # the Listen is open before the Set (updates only: no snapshot)
        for value in (True, False, True):
            headers = {"Content-Type": "application/json"}
            async with http.put(
                "/api/v1/services/board/properties/lit", json={"value": value}, headers=headers
            ) as response:
                assert response.status == 200
        event = await asyncio.wait_for(first, 10)
        assert event.property == "lit"
    finally:
        first.cancel()
        await stream.aclose()


async def test_wildcards_follow_what_a_grpc_listen_follows(http: aiohttp.ClientSession) -> None:
    async with http.get(EVENTS, params={"sel": "board/*"}) as response:
        snapshot = await SseReader(response).values_until_sync()
    assert sorted(m.data["path"] for m in snapshot) == ["level", "lit", "note", "point"]  # not the action


async def test_a_wildcard_service_matches_every_service(http: aiohttp.ClientSession) -> None:
    async with http.get(EVENTS, params={"sel": "*/note"}) as response:
        snapshot = await SseReader(response).values_until_sync()
    assert [(m.data["service"], m.data["path"]) for m in snapshot] == [("board", "note")]


async def test_last_event_id_resumes_with_the_snapshot_marked_as_a_gap(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    headers = {"Last-Event-ID": "41"}
    async with http.get(EVENTS, params={"sel": "board/note"}, headers=headers) as response:
        events = SseReader(response)
        snapshot = await events.values_until_sync()
        assert [m.data["gap"] for m in snapshot] == [True]
        await grpc_client.set("board", "note", "after the resume")
        change = await events.until("value")
        assert (change.data["value"], change.data["gap"]) == ("after the resume", False)


async def test_an_idle_stream_gets_heartbeats(http: aiohttp.ClientSession) -> None:
    async with http.get(EVENTS, params={"sel": "board/level"}) as response:
        events = SseReader(response)
        await events.values_until_sync()
        beat = await events.next()
        assert (beat.event, beat.comment) == ("comment", "heartbeat")
        again = await events.next()
        assert (again.event, again.comment) == ("comment", "heartbeat")


async def test_a_listen_that_fails_sends_an_error_event_and_ends(http: aiohttp.ClientSession) -> None:
    async with http.get(EVENTS, params={"sel": "nosuch/location"}) as response:
        assert response.status == 200
        events = SseReader(response)
        error = await events.next()
        assert error.event == "error"
        assert error.data["code"] == "NOT_FOUND" and "nosuch" in error.data["message"]
        with pytest.raises(AssertionError, match="ended"):
            await events.next()


@pytest.mark.parametrize(
    ("query", "wrong"),
    [
        ("", "at least one selector"),
        ("?sel=board", "SERVICE/PATH"),
        ("?sel=/note", "SERVICE/PATH"),
        ("?sel=board/note&since=3", "unknown query key"),
        ("?sel=bo%20ard/note", "service"),
        ("?sel=board/a..b", "property pattern"),
    ],
)
async def test_a_bad_selector_is_a_json_error_before_any_event(
    http: aiohttp.ClientSession, query: str, wrong: str
) -> None:
    async with http.get(EVENTS + query) as response:
        assert response.status == 400
        body = await response.json()
    assert body["error"]["code"] == "INVALID_ARGUMENT"
    assert wrong in body["error"]["message"]


async def test_shutdown_ends_each_stream_with_unavailable(gateway_process: StartGateway) -> None:
    gw = gateway_process(CONFIG)
    async with (
        aiohttp.ClientSession(base_url=gw.http_url) as http,
        http.get(EVENTS, params={"sel": "board/note"}) as response,
    ):
        events = SseReader(response)
        await events.values_until_sync()
        assert await asyncio.to_thread(gw.stop) == 0
        error = await events.until("error")
        assert error.data == {"code": "UNAVAILABLE", "message": "gateway shutting down"}
