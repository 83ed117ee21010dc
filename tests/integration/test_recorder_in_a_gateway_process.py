"""The recorder in a real gateway process: a recording started and stopped through the SDK, read
back with the ``mcap`` library and checked against what a Listen of the same selectors heard at
the same time; files that rotate under a small disk budget; a gateway killed mid-recording (its
writer process finishes the file) and a writer process killed (the recording fails, the next one
gets a new process); a caller that may not read what it asks to record.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import jsonschema
import psutil
import pytest
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader
from mcap.summary import Summary
from support.gateway_process import GatewayProcess, StartGateway
from support.waiting import eventually

from clients.aio import AsyncClient
from clients.errors import AlreadyExists, FailedPrecondition, InvalidArgument, NotFound, PermissionDenied
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.apps.recorder.layout import EVENTS_TOPIC
from services.apps.recorder.reading import RecordedEvent, recorded_events

pytestmark = pytest.mark.slow

#: What the tests record: every robot's location (the swarm's too) and the sensor's properties.
SELECTORS = ("*/location", "thermo1/*")
DRIVE = "<marker><location>(6 6)</location></marker>"
HOME = "<marker><location>(0 0)</location></marker>"

ROBOTS = """
[[services]]
name = "scout1"
type = "sim-robot"

[[services]]
name = "scout2"
type = "sim-robot"
options = {{ start = [1.0, 0.0] }}

[[services]]
name = "recorder"
type = "recorder"
[services.options]
folder = "{folder}"
max_file_bytes = 65536
max_file_seconds = {seconds}
max_total_bytes = {budget}
"""


async def recordings(client: AsyncClient) -> dict[str, dict[str, Any]]:
    listed = json.loads(str(await client.get("recorder", "recordings")))
    return {r["name"]: r for r in listed}


async def heard(client: AsyncClient, selectors: tuple[str, ...], into: list[Any]) -> None:
    """Append every event a Listen of ``selectors`` hears, until cancelled."""
    first, *more = [tuple(s.split("/", 1)) for s in selectors]
    async for event in client.listen(*first, *more):  # type: ignore[arg-type]
        into.append(event)


def by_property(events: list[Any]) -> dict[tuple[str, str], list[Any]]:
    out: dict[tuple[str, str], list[Any]] = defaultdict(list)
    for e in events:
        out[e.service, getattr(e, "property", None) or e.path].append(e)
    return out


def assert_accounted_for(recorded: list[RecordedEvent], listened: list[Any]) -> None:
    """The recording and the Listen heard the same changes of each property, in the same order,
    but for the values either side conflated (a reader that fell behind gets the latest value,
    counting those it replaced): a value one heard and the other did not is counted as conflated
    by the other."""
    assert recorded, "nothing was recorded"
    heard_by_listen = by_property(listened)
    for key, events in by_property(recorded).items():
        heard = heard_by_listen.get(key)
        assert heard, f"{key} was recorded, and the Listen never heard it"
        heard_values = [e.value for e in heard]
        recorded_values = [e.value for e in events]
        only_recorded = [v for v in recorded_values if v not in set(heard_values)]
        assert len(only_recorded) <= sum(e.conflated for e in heard), (
            f"{key}: recorded, never heard: {only_recorded}"
        )
        # The values both heard, in the same order.
        common = [v for v in recorded_values if v in set(heard_values)]
        position = -1
        for value in common:
            found = heard_values.index(value, position + 1) if value in heard_values[position + 1 :] else -1
            assert found > position, f"{key}: {value!r} recorded out of the Listen's order"
            position = found
        first = heard_values.index(common[0]) if common else 0
        during = heard_values[first : position + 1]
        only_heard = [v for v in during if v not in set(recorded_values)]
        assert len(only_heard) <= sum(e.conflated for e in events), (
            f"{key}: heard, never recorded: {only_heard}"
        )


def check_channels(path: Path) -> dict[str, int]:
    """Every message of the file is valid: JSON against its channel's schema, protobuf decoding
    with its schema's type; the count of messages by topic."""
    counts: dict[str, int] = defaultdict(int)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] += 1
            assert schema is not None
            if channel.message_encoding == "json":
                jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            elif schema.name == "propertyservice.v1.Event":
                assert pb.Event.FromString(message.data).service
            elif schema.name == "foxglove.PoseInFrame":
                assert PoseInFrame.FromString(message.data).frame_id == "world"
            elif schema.name == "foxglove.SceneUpdate":
                assert SceneUpdate.FromString(message.data).entities
            else:
                pytest.fail(f"unexpected channel {channel.topic} of schema {schema.name}")
    return dict(counts)


async def test_a_recording_of_the_swarm_driving_holds_every_change_a_listen_heard(
    demo_gateway: GatewayProcess,
) -> None:
    name = f"swarm-{time.time_ns()}"
    async with AsyncClient(demo_gateway.address, timeout=15.0) as client:
        folder = Path(str(await client.get("recorder", "folder")))
        listened: list[Any] = []
        listening = asyncio.create_task(heard(client, SELECTORS, listened))
        try:
            await eventually(
                lambda: asyncio.sleep(0, len(listened)), lambda n: n > 0, what="the Listen's first values"
            )
            await client.set("swarm", "behaviors.moveto", DRIVE, formation="line")
            answer = await client.set("recorder", "start", " ".join(SELECTORS), name=name)
            assert answer == name
            assert (await recordings(client))[name]["state"] == "recording"
            await asyncio.sleep(3.0)
            assert await client.set("recorder", "stop", name) == name
            await asyncio.sleep(0.5)  # the Listen hears what the recording heard last
        finally:
            listening.cancel()
            await asyncio.gather(listening, return_exceptions=True)
            await client.set("swarm", "behaviors.moveto", HOME, formation="line")
        listed = (await recordings(client))[name]
    try:
        assert listed["state"] == "stopped"
        assert listed["selectors"] == list(SELECTORS)
        assert listed["files"] == [f"{name}/{name}-0001.mcap"]
        assert listed["dropped"] == 0
        path = folder / listed["files"][0]
        assert listed["size"] == path.stat().st_size
        recorded = list(recorded_events(path))
        assert len(recorded) == listed["events"]
        moved = {key for key, events in by_property(recorded).items() if len({e.value for e in events}) > 1}
        assert {("scout1", "location"), ("scout2", "location"), ("swarm", "location")} <= moved
        assert any(service == "thermo1" for service, _ in by_property(recorded))
        assert_accounted_for(recorded, listened)

        counts = check_channels(path)
        assert counts[EVENTS_TOPIC] == len(recorded) and sum(counts.values()) == listed["messages"]
        assert (
            counts["/scout1/location"]
            == counts["/scout1/pose"]
            == len(by_property(recorded)["scout1", "location"])
        )
        locations = sum(len(v) for (s, p), v in by_property(recorded).items() if p == "location")
        assert counts["/scene"] == locations
    finally:
        shutil.rmtree(folder / name, ignore_errors=True)


async def test_files_rotate_and_the_oldest_go_when_the_disk_budget_is_spent(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    budget = 120_000
    gw = gateway_process(ROBOTS.format(folder=folder, seconds=0.5, budget=budget))
    async with AsyncClient(gw.address, timeout=15.0) as client:
        await client.set("scout1", "behaviors.moveto", DRIVE)
        await client.set("scout2", "behaviors.moveto", DRIVE)
        await client.set("recorder", "start", "scout1/* scout2/*", name="long")

        async def spent() -> dict[str, Any]:
            return (await recordings(client))["long"]

        listed = await eventually(
            spent,
            lambda r: bool(r["files"]) and r["files"][0] != "long/long-0001.mcap",
            within=30,
            what="a file removed",
        )
        await client.set("recorder", "stop", "*")
        listed = (await recordings(client))["long"]
    assert listed["state"] == "stopped"
    numbers = [int(f.rsplit("-", 1)[1].removesuffix(".mcap")) for f in listed["files"]]
    assert numbers == list(range(numbers[0], numbers[0] + len(numbers)))  # the newest kept, in order
    on_disk = sorted(p.name for p in (folder / "long").iterdir())
    assert on_disk == [f.split("/")[1] for f in listed["files"]]
    total = sum(p.stat().st_size for p in (folder / "long").iterdir())
    assert total <= budget
    for name in on_disk:
        assert check_channels(folder / "long" / name)[EVENTS_TOPIC] > 0


def streamed_events(path: Path) -> int:
    """The ``/_events`` messages the library's own reader finds streaming the file as written (a
    file with no summary to seek by)."""
    streamed = 0
    with open(path, "rb") as f, contextlib.suppress(EndOfFile):  # the cut-off tail ends it
        for _, channel, _ in NonSeekingReader(f, validate_crcs=False).iter_messages(log_time_order=False):
            streamed += channel.topic == EVENTS_TOPIC
    return streamed


def summary_of(path: Path) -> Summary | None:
    """The summary a finished file ends with (None: the file was not finished)."""
    with open(path, "rb") as f:
        return make_reader(f).get_summary()


def writer_process_of(gw: GatewayProcess) -> psutil.Process:
    """The recorder's writer process, a child of the gateway's."""
    for child in psutil.Process(gw.proc.pid).children():
        if any("services.apps.recorder.process" in part for part in child.cmdline()):
            return child
    raise AssertionError("the gateway has no writer process")


async def test_a_gateway_killed_mid_recording_leaves_a_finished_file_and_no_writer_behind(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    gw = gateway_process(ROBOTS.format(folder=folder, seconds=600, budget=1 << 30))
    async with AsyncClient(gw.address, timeout=15.0) as client:
        await client.set("scout1", "behaviors.moveto", DRIVE)
        listened: list[Any] = []
        listening = asyncio.create_task(heard(client, ("scout1/location",), listened))
        await client.set("recorder", "start", "scout1/location", name="cut")
        await asyncio.sleep(2.5)
        writer = writer_process_of(gw)
        gw.proc.send_signal(signal.SIGKILL)
        gw.proc.wait(10)
        await asyncio.gather(listening, return_exceptions=True)
    # The writer sees its input end, finishes the file and ends: it never outlives the gateway.
    await asyncio.to_thread(writer.wait, 30)
    path = folder / "cut" / "cut-0001.mcap"
    summary = summary_of(path)
    assert summary is not None, "the file was left without its summary"
    recorded = list(recorded_events(path))
    assert len(recorded) >= 20  # 20 Hz while it drives
    assert_accounted_for(recorded, listened)
    assert streamed_events(path) == len(recorded)
    assert summary.statistics is not None
    events_channel = next(c.id for c in summary.channels.values() if c.topic == EVENTS_TOPIC)
    assert summary.statistics.channel_message_counts[events_channel] == len(recorded)


async def test_a_writer_process_that_dies_fails_its_recording_and_the_next_start_gets_a_new_one(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    gw = gateway_process(ROBOTS.format(folder=folder, seconds=600, budget=1 << 30))
    async with AsyncClient(gw.address, timeout=15.0) as client:
        await client.set("scout1", "behaviors.moveto", DRIVE)
        await client.set("recorder", "start", "scout1/location", name="first")
        await eventually(
            lambda: recordings(client), lambda r: r["first"]["events"] > 0, within=30, what="events written"
        )
        await asyncio.sleep(1.5)  # a chunk is closed
        writer = writer_process_of(gw)
        writer.kill()
        listed = await eventually(
            lambda: recordings(client),
            lambda r: r["first"]["state"] != "recording",
            within=30,
            what="the recording failed",
        )
        assert listed["first"]["state"] == "failed: the writer process ended"
        assert "killed by SIGKILL" in listed["first"]["reason"]
        with pytest.raises(FailedPrecondition, match="failed: the writer process ended already"):
            await client.set("recorder", "stop", "first")

        await client.set("recorder", "start", "scout1/location", name="second")
        await asyncio.sleep(1.5)
        assert writer_process_of(gw).pid != writer.pid
        assert await client.set("recorder", "stop", "second") == "second"
        listed = await recordings(client)
    assert listed["second"]["state"] == "stopped"
    recorded = list(recorded_events(folder / "second" / "second-0001.mcap"))
    assert len(recorded) == listed["second"]["events"] > 0
    # What the first one wrote before its writer died stays readable up to its last closed chunk.
    assert streamed_events(folder / "first" / "first-0001.mcap") > 0


RULES = """
[[services]]
name = "scout1"
type = "sim-robot"

[[services]]
name = "secret"
type = "sim-robot"

[[services]]
name = "recorder"
type = "recorder"
options = {{ folder = "{folder}" }}

[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[rules]]
subject = "operator"
service = "secret"
operations = ["read", "write", "invoke"]
effect = "deny"

[[rules]]
subject = "operator"
service = "*"
operations = ["read", "write", "invoke"]
effect = "permit"
"""
SECRET = "a shared secret of the lab, long enough for HS256"


async def test_a_caller_records_only_what_it_may_read(gateway_process: StartGateway, tmp_path: Path) -> None:
    import jwt

    from clients.credentials import ClientCredentials

    (tmp_path / "jwt.secret").write_text(SECRET)
    folder = tmp_path / "recordings"
    gw = gateway_process(RULES.format(folder=folder))
    token = jwt.encode(
        {"sub": "operator", "iss": "lab", "exp": int(time.time()) + 600}, SECRET, algorithm="HS256"
    )
    async with AsyncClient(gw.address, timeout=15.0, credentials=ClientCredentials(token=token)) as operator:
        with pytest.raises(PermissionDenied):
            await operator.set("recorder", "start", "secret/location", name="refused")
        assert "refused" not in await recordings(operator)
        await operator.set("recorder", "start", "*/location", name="mine")
        await asyncio.sleep(1.5)
        await operator.set("recorder", "stop", "mine")
    recorded = list(recorded_events(folder / "mine" / "mine-0001.mcap"))
    assert {e.service for e in recorded} == {"scout1"}


async def test_bad_starts_and_stops_get_clear_errors_and_leave_nothing_behind(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    gw = gateway_process(ROBOTS.format(folder=folder, seconds=600, budget=1 << 30))
    async with AsyncClient(gw.address, timeout=15.0) as client:
        with pytest.raises(InvalidArgument, match="SERVICE/PATH"):
            await client.set("recorder", "start", "location")
        with pytest.raises(InvalidArgument, match="give what to record"):
            await client.set("recorder", "start", "  ")
        with pytest.raises(InvalidArgument, match="bad recording name"):
            await client.set("recorder", "start", "scout1/location", name="../up")
        with pytest.raises(NotFound):
            await client.set("recorder", "start", "nosuch/location", name="ghost")
        assert not (folder / "ghost").exists()
        with pytest.raises(NotFound, match="no recording named"):
            await client.set("recorder", "stop", "ghost")
        await client.set("recorder", "start", "scout1/location", name="once")
        with pytest.raises(AlreadyExists):
            await client.set("recorder", "start", "scout2/location", name="once")
        await client.set("recorder", "stop", "once")
        with pytest.raises(FailedPrecondition, match="stopped already"):
            await client.set("recorder", "stop", "once")
        assert list(await recordings(client)) == ["once"]
    assert sorted(p.name for p in folder.iterdir()) == ["once"]


def tiny_tmpfs_or_skip(mount_point: Path) -> str:
    """``unshare``, once it has shown that it can mount a tmpfs on ``mount_point`` in a user
    namespace of its own; else the test skips, saying why."""
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("a full disk needs a tiny tmpfs: unshare (util-linux) is not installed")
    probe = subprocess.run(
        [unshare, "-rm", "sh", "-c", f"mount -t tmpfs -o size=32k tmpfs {mount_point}"],
        capture_output=True,
        text=True,
        check=False,
    )
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a tiny tmpfs in a user namespace here: {probe.stderr.strip()}")
    return unshare


async def test_a_full_disk_fails_the_recording_and_says_so(tmp_path: Path) -> None:
    """The disk is a real one, a 32 KiB tmpfs mounted in a user namespace of the gateway's own
    (``unshare -rm``); where user namespaces or unshare are missing, the test skips saying why."""
    small = tmp_path / "small"
    small.mkdir()
    unshare = tiny_tmpfs_or_skip(small)
    config = tmp_path / "gateway.toml"
    config.write_text(ROBOTS.format(folder=small / "recordings", seconds=600, budget=1 << 30))
    serve = f"mount -t tmpfs -o size=32k tmpfs {small} && exec {sys.executable} -m gateway.cli serve"
    gw = GatewayProcess(
        [unshare, "-rm", "sh", "-c", f'{serve} --config "$0" --listen 127.0.0.1:0', str(config)]
    )
    try:
        gw.wait_ready()
        gw.expect_in_log(
            "could not finish full-0001.mcap"
        )  # a warning line: the summary found no room either
        async with AsyncClient(gw.address, timeout=15.0) as client:
            await client.set("scout1", "behaviors.moveto", DRIVE)
            await client.set("scout2", "behaviors.moveto", DRIVE)
            await client.set("recorder", "start", "scout1/* scout2/*", name="full")

            async def state() -> dict[str, Any]:
                return (await recordings(client))["full"]

            listed = await eventually(
                state, lambda r: r["state"] != "recording", within=60, what="a full disk"
            )
            assert listed["state"] == "failed: disk full"
            assert "No space left on device" in listed["reason"]
            assert listed["events"] > 0
            # The gateway goes on serving.
            assert await client.get("scout1", "location")
    finally:
        gw.stop()


async def test_a_recording_plays_back_as_live_services_in_another_gateway(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    recorder = gateway_process(ROBOTS.format(folder=folder, seconds=600, budget=1 << 30))
    async with AsyncClient(recorder.address, timeout=15.0) as client:
        await client.set("scout1", "behaviors.moveto", DRIVE)
        await client.set("recorder", "start", "scout1/location", name="drive", max_duration=2.0)
        await eventually(
            lambda: recordings(client), lambda r: r["drive"]["state"] == "stopped", within=30, what="the end"
        )
    recorded = list(recorded_events(folder / "drive" / "drive-0001.mcap"))
    assert len({e.value for e in recorded}) > 5  # it drove

    player = gateway_process(
        f"""
        [[services]]
        name = "replay"
        type = "replay"
        options = {{ recording = "{folder / "drive"}", autostart = false }}
        """
    )
    async with AsyncClient(player.address, timeout=15.0) as client:
        assert await client.get("replay", "services") == "(scout1)"
        duration = float(str(await client.get("replay", "duration")))
        assert duration == pytest.approx((recorded[-1].log_time_ns - recorded[0].log_time_ns) / 1e9, abs=0.01)
        middle = round(duration / 2, 3)
        await client.set("replay", "seek", str(middle))
        # The value the recording held then: its last change at or before that offset.
        first = recorded[0].log_time_ns
        then = [e.value for e in recorded if e.log_time_ns - first <= middle * 1e9][-1]
        assert await client.get("scout1", "location") == then
