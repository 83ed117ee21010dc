"""A recording played back as live services by a real gateway process, read as a user reads any
service: the SDK over gRPC, the HTTP front end (Get, model, Server-Sent Events) and psctl."""

from __future__ import annotations

import asyncio
import base64
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from support.gateway_process import GatewayProcess, StartGateway, start_gateway
from support.psctl import psctl
from support.recordings import CAMERA, FRAME_A, FRAME_B, ROBOT, Recorded, swarm_changes, swarm_recording
from support.sse import SseReader

from clients import AsyncClient
from clients.aio.events import SYNC, Event
from clients.errors import FailedPrecondition, InvalidArgument, NotFound
from services.kernel.values import Value

pytestmark = pytest.mark.timeout(120)

#: The recording's length: its last change is 4.1 s after its first.
DURATION_S = 4.1
#: What the Listens follow: every property of the swarm (a ``*`` matches one segment of a path).
SELECTORS = [
    ("scout1", "*"),
    ("scout1", "sensors.*"),
    ("scout2", "*"),
    ("scout2", "sensors.*"),
    ("cam1", "frame"),
]


def replay_config(recording: Path, *, speed: float = 1.0, prefix: str = "") -> str:
    """A replay of ``recording`` that stands at the start until it is told to play."""
    return f"""
        [[services]]
        name = "replay"
        type = "replay"
        options = {{ recording = "{recording}", speed = {speed}, autostart = false, prefix = "{prefix}" }}
    """


def state_at(at_s: float) -> dict[tuple[str, str], Value]:
    """Each property's value at ``at_s`` seconds into the recording (removed ones absent)."""
    state: dict[tuple[str, str], Value] = {}
    for change in sorted(swarm_changes(), key=lambda c: c.log_time_ns):
        if change.at_s > at_s:
            break
        if change.removed:
            state.pop((change.service, change.path), None)
        else:
            state[(change.service, change.path)] = change.value
    return state


def changes_after(at_s: float) -> dict[tuple[str, str], list[Recorded]]:
    """The changes of each property after ``at_s``, in order."""
    after: dict[tuple[str, str], list[Recorded]] = {}
    for change in sorted(swarm_changes(), key=lambda c: c.log_time_ns):
        if change.at_s > at_s:
            after.setdefault((change.service, change.path), []).append(change)
    return after


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return swarm_recording(tmp_path_factory.mktemp("recordings"))


@pytest.fixture(scope="module")
def paused(tmp_path_factory: pytest.TempPathFactory, recording: Path) -> Iterator[GatewayProcess]:
    """One gateway whose replay stands still at the start: for the tests that only read."""
    gw = start_gateway(tmp_path_factory.mktemp("paused"), replay_config(recording))
    yield gw
    gw.stop()


@pytest.fixture
async def client(paused: GatewayProcess) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(paused.address, timeout=10) as sdk:
        yield sdk


def http_value(body: dict[str, object]) -> Value:
    """The value of an HTTP Get's answer: text, or the bytes of a binary one."""
    if "data" in body:
        return base64.b64decode(str(body["data"]))
    return str(body["value"])


async def test_replayed_services_describe_themselves_as_recorded_with_the_replay_mark(
    client: AsyncClient, paused: GatewayProcess
) -> None:
    listed = await client.get_names("registry", "services")
    assert {"scout1", "scout2", "cam1", "replay"} <= set(listed), listed
    async with aiohttp.ClientSession(base_url=paused.http_url) as http:
        for name, recorded in (("scout1", ROBOT), ("scout2", ROBOT), ("cam1", CAMERA)):
            model = await client.describe(name)
            assert model.properties == recorded.properties
            assert model.type == recorded.type
            assert "replayed from swarm" in model.doc
            async with http.get(f"/api/v1/services/{name}/model") as response:
                assert response.status == 200
                body = await response.json()
            assert body["doc"] == model.doc
            assert [p["name"] for p in body["properties"]] == [p.name for p in recorded.properties]
        async with http.get("/api/v1/services") as response:
            services = {s["name"]: s for s in (await response.json())["services"]}
        assert services["scout1"]["type"] == "mobile_robot"
        assert services["scout1"]["address"] == "replay:swarm"


async def test_a_replay_that_stands_at_the_start_answers_gets_with_the_first_recorded_values(
    client: AsyncClient, paused: GatewayProcess
) -> None:
    expected = state_at(0.0)
    async with aiohttp.ClientSession(base_url=paused.http_url) as http:
        for (service, path), value in expected.items():
            assert await client.get(service, path) == value, (service, path)
            async with http.get(f"/api/v1/services/{service}/properties/{path}") as response:
                assert response.status == 200, await response.text()
                assert http_value(await response.json()) == value, (service, path)
    assert await client.get("cam1", "frame") == FRAME_A
    assert await client.get("replay", "position") == "0"
    assert await client.get("replay", "playing") == "false"


async def test_a_set_on_a_replayed_service_is_failed_precondition_naming_the_recording(
    client: AsyncClient, paused: GatewayProcess
) -> None:
    with pytest.raises(FailedPrecondition, match=r"scout1\.speed is replayed from swarm: read-only"):
        await client.set("scout1", "speed", 1.0)
    with pytest.raises(FailedPrecondition, match="replayed from swarm: read-only"):
        await client.set("scout1", "behaviors.moveto", "<marker><location>(1 1)</location></marker>")
    with pytest.raises(NotFound):
        await client.set("scout1", "no.such", "1")
    async with aiohttp.ClientSession(base_url=paused.http_url) as http:
        async with http.put("/api/v1/services/scout2/properties/speed", json={"value": "2"}) as response:
            assert response.status == 400
            error = (await response.json())["error"]
        assert error["code"] == "FAILED_PRECONDITION"
        assert "replayed from swarm: read-only" in error["message"]
    # Nothing changed: the recorded value stands.
    assert await client.get("scout2", "speed") == "0.8"


def test_psctl_lists_and_reads_the_replayed_services(paused: GatewayProcess) -> None:
    listing = psctl(paused.address, "ls")
    assert listing.returncode == 0, listing.stderr
    for name in ("scout1", "scout2", "cam1", "replay"):
        assert name in listing.stdout
    properties = psctl(paused.address, "ls", "scout1")
    assert properties.returncode == 0, properties.stderr
    assert "sensors.battery" in properties.stdout
    read = psctl(paused.address, "get", "scout1", "location")
    assert read.returncode == 0, read.stderr
    assert "(0 0 0 0 0 0)" in read.stdout
    refused = psctl(paused.address, "set", "scout1", "speed", "1")
    assert refused.returncode != 0
    assert "replayed from swarm: read-only" in refused.stderr


async def _opened(events: Any, within: float = 10) -> Any:
    """``events`` (a Listen with marks) once its current values are read: what follows are changes."""
    async with asyncio.timeout(within):
        async for item in events:
            if item is SYNC:
                return events
    raise AssertionError("the Listen ended before its current values")


async def _heard(events: Any, value: str, within: float = 20) -> None:
    """Read ``events`` until a change carries ``value``; then close them."""
    async with asyncio.timeout(within):
        async for item in events:
            if isinstance(item, Event) and item.value == value:
                break
    await events.aclose()


async def _sdk_changes(events: AsyncIterator[Event | object], into: list[Event]) -> None:
    async for item in events:
        if isinstance(item, Event):
            into.append(item)


async def _sse_changes(reader: SseReader, into: list[dict[str, object]]) -> None:
    while True:
        message = await reader.next(within=30)
        if message.event == "value":
            into.append(message.data)


def _accounted(received: list[tuple[Value, bool, bool, int]], expected: list[Recorded]) -> None:
    """``received`` (value, gap, removed, conflated) is ``expected`` in order, but for values a slow
    reader's stream conflated, which it counts."""
    assert len(received) + sum(c for *_, c in received) == len(expected), (received, expected)
    index = 0
    for value, gap, removed, conflated in received:
        index += conflated
        change = expected[index]
        assert (value, removed) == (change.value, change.removed), (received, expected)
        if change.gap and not conflated:
            assert gap, change
        index += 1


async def test_listens_over_grpc_and_http_see_every_recorded_change_with_its_gap_and_removal(
    gateway_process: StartGateway, recording: Path
) -> None:
    gw = gateway_process(replay_config(recording, speed=2.0))
    expected = changes_after(0.0)
    async with (
        AsyncClient(gw.address, timeout=10) as sdk,
        aiohttp.ClientSession(base_url=gw.http_url) as http,
    ):
        stream = sdk.listen(*SELECTORS[0], *SELECTORS[1:], marks=True)
        first: list[Event] = []
        async with asyncio.timeout(10):
            async for item in stream:
                if item is SYNC:
                    break
                assert isinstance(item, Event)
                first.append(item)
        assert {(e.service, e.property): e.value for e in first} == state_at(0.0)
        query = "&".join(f"sel={s}/{p}" for s, p in SELECTORS)
        async with http.get(f"/api/v1/events?{query}", timeout=aiohttp.ClientTimeout(total=60)) as response:
            sse = SseReader(response)
            snapshot = await sse.values_until_sync()
            assert {(m.data["service"], m.data["path"]) for m in snapshot} == set(state_at(0.0))
            sdk_events: list[Event] = []
            sse_events: list[dict[str, object]] = []
            readers = [
                asyncio.ensure_future(_sdk_changes(stream, sdk_events)),
                asyncio.ensure_future(_sse_changes(sse, sse_events)),
            ]
            playing = await _opened(sdk.listen("replay", "playing", marks=True))
            started = time.monotonic()
            await sdk.set("replay", "play", "")
            await _heard(playing, "false")
            took = time.monotonic() - started
            await asyncio.sleep(0.3)  # the last changes reach both streams
            for reader in readers:
                reader.cancel()
            await asyncio.gather(*readers, return_exceptions=True)
            await stream.aclose()
    # At twice the recorded pace, the 4.1 s took about 2 s (a loaded machine may take longer).
    assert DURATION_S / 2 - 0.1 <= took <= 10
    for key, changes in expected.items():
        over_grpc = [
            (e.value, e.gap, e.removed, e.conflated) for e in sdk_events if (e.service, e.property) == key
        ]
        _accounted(over_grpc, changes)
        over_http = [
            (
                base64.b64decode(str(m["data"])) if "data" in m else str(m["value"]),
                bool(m["gap"]),
                bool(m["removed"]),
                int(str(m["conflated"])),
            )
            for m in sse_events
            if (m["service"], m["path"]) == key
        ]
        _accounted(over_http, changes)
    assert {(e.service, e.property) for e in sdk_events} == set(expected)


async def test_seek_speed_pause_and_loop_steer_the_replay_and_position_follows(
    gateway_process: StartGateway, recording: Path
) -> None:
    gw = gateway_process(replay_config(recording))
    async with AsyncClient(gw.address, timeout=10) as sdk:
        assert await sdk.get_number("replay", "duration") == DURATION_S
        await sdk.set("replay", "seek", 2.0)
        assert await sdk.get_number("replay", "position") == 2.0
        for (service, path), value in state_at(2.0).items():
            assert await sdk.get(service, path) == value, (service, path)
        assert await sdk.get("cam1", "frame") == FRAME_B

        # A seek back tells a listener the value there, marked as a gap: values were skipped.
        listen = await _opened(sdk.listen("scout1", "location", marks=True))
        await sdk.set("replay", "seek", 1.0)
        async with asyncio.timeout(10):
            event = await anext(listen)
        assert isinstance(event, Event)
        assert event.value == state_at(1.0)[("scout1", "location")]
        assert event.gap
        await listen.aclose()

        with pytest.raises(InvalidArgument, match=r"runs from 0 to 4\.100 s"):
            await sdk.set("replay", "seek", 99)
        with pytest.raises(InvalidArgument):
            await sdk.set("replay", "speed", 0)

        await sdk.set("replay", "speed", 4)
        assert await sdk.get_number("replay", "speed") == 4.0
        await sdk.set("replay", "play", "")
        assert await sdk.get("replay", "playing") == "true"
        await asyncio.sleep(0.5)
        moved = await sdk.get_number("replay", "position")
        assert 1.5 <= moved <= DURATION_S
        await sdk.set("replay", "pause", "")
        held = await sdk.get_number("replay", "position")
        await asyncio.sleep(0.3)
        assert await sdk.get_number("replay", "position") == held
        assert await sdk.get("replay", "playing") == "false"

        # Looping: the position comes back to the start, and the replay plays on.
        await sdk.set("replay", "loop", True)
        await sdk.set("replay", "speed", 20)
        await sdk.set("replay", "play", "")
        positions = sdk.listen("replay", "position")
        last = 0.0
        async with asyncio.timeout(15):
            async for event in positions:
                now = float(str(event.value))
                if now < last:
                    break  # back at the start
                last = now
        await positions.aclose()
        assert last > DURATION_S / 2
        assert await sdk.get("replay", "playing") == "true"

        # Without the loop it stops at the end, with the last recorded values.
        playing = await _opened(sdk.listen("replay", "playing", marks=True))
        await sdk.set("replay", "loop", False)
        await _heard(playing, "false")
        assert await sdk.get_number("replay", "position") == DURATION_S
        for (service, path), value in state_at(DURATION_S).items():
            assert await sdk.get(service, path) == value, (service, path)
        with pytest.raises(NotFound, match="removed"):
            await sdk.get("scout2", "status")


async def test_a_prefix_serves_the_recording_beside_the_live_services_of_the_same_names(
    gateway_process: StartGateway, recording: Path
) -> None:
    gw = gateway_process(
        f"""
        [[services]]
        name = "scout1"
        type = "sim-robot"
        options = {{ start = [7.0, 7.0] }}
        {replay_config(recording, prefix="was-")}
        """
    )
    async with AsyncClient(gw.address, timeout=10) as sdk:
        assert {"scout1", "was-scout1", "was-scout2", "was-cam1"} <= set(
            await sdk.get_names("registry", "services")
        )
        assert await sdk.get("was-scout1", "location") == state_at(0.0)[("scout1", "location")]
        assert "replayed from swarm" in (await sdk.describe("was-scout1")).doc
        assert "replayed" not in (await sdk.describe("scout1")).doc
        assert (await sdk.get_vector("scout1", "location"))[:2].tolist() == [7.0, 7.0]
        await sdk.set("scout1", "speed", 0.25)  # the live robot takes Sets
        with pytest.raises(FailedPrecondition):
            await sdk.set("was-scout1", "speed", 0.25)
