"""The recorder's parts in one process: one file's layout read back with the ``mcap`` library, the
events read back for history, a file cut short, a full disk, the disk budget, a full intake, the
batches to the writer process and that process's loop on real pipes."""

from __future__ import annotations

import asyncio
import io
import json
import os
import threading
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.apps.recorder.budget import DiskBudget
from services.apps.recorder.feed import BATCH_EVENTS, BATCH_SECONDS, RecordingFeed
from services.apps.recorder.frames import EventFields, FrameError, FrameReader, frame
from services.apps.recorder.layout import (
    EVENTS_TOPIC,
    RECORDING_METADATA,
    SERVICE_METADATA,
    RecordingFile,
    ServiceInfo,
)
from services.apps.recorder.process import WriterProcess
from services.apps.recorder.reading import RecordedEvent, events_between, recorded_events
from services.apps.recorder.writer import Limits, RecordingWriter
from services.kernel.follow import FollowedEvent
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.model_codec import model_from_text
from services.kernel.pose import quaternion

ROBOT = ServiceModel(
    "mobile_robot",
    (
        PropertyModel("location", "vector", Access.READ, length=6, unit="m", doc="where it is"),
        PropertyModel("battery", "number", Access.READ, unit="%", minimum=0, maximum=100),
        PropertyModel("moving", "boolean", Access.READ),
        PropertyModel("camera", "bytes", Access.READ, media_type="image/jpeg"),
        PropertyModel("name", "text", Access.READ_WRITE),
    ),
    doc="a robot",
)
INFO = ServiceInfo("mobile_robot", ROBOT)
T0 = 1_800_000_000_000_000_000


def event(
    seq: int, path: str, value: str | bytes, *, service: str = "scout1", **flags: object
) -> FollowedEvent:
    return FollowedEvent(service, path, value, seq, T0 + seq * 1_000_000, **flags)  # type: ignore[arg-type]


def write_file(path: Path, events: list[FollowedEvent], *, finish: bool = True) -> RecordingFile:
    stream = open(path, "xb")  # noqa: SIM115 - closed below, or left open as a killed writer leaves it
    recording = RecordingFile(
        stream, name="run1", selectors=["*/location", "scout1/*"], started_ns=T0, index=1, version="9.9"
    )
    for e in events:
        if not recording.has_service(e.service):
            recording.add_service(e.service, INFO)
        recording.write(e, e.time_ns + 500, INFO)
    if finish:
        recording.finish()
        stream.close()
    return recording


SOME = [
    event(1, "location", "(1 2 0 0 0 1.5)"),
    event(2, "battery", "87.5"),
    event(3, "moving", "true"),
    event(4, "camera", b"\xff\xd8\xff\xe0jpeg"),
    event(5, "name", "scout one"),
    event(6, "location", "(1.5 2 0 0 0 1.5)", conflated=2),
    event(7, "location", "(2 2 0 0 0 1.5)", service="scout2", gap=True),
    event(8, "battery", "", removed=True),
]


def test_a_recording_file_holds_metadata_channels_and_messages_every_reader_understands(
    tmp_path: Path,
) -> None:
    path = tmp_path / "run1-0001.mcap"
    write_file(path, SOME)

    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().library == "psgateway recorder 9.9"
        assert reader.get_header().profile == ""
        metadata = list(reader.iter_metadata())
        summary = reader.get_summary()
        assert summary is not None
        messages = list(reader.iter_messages(log_time_order=False))

    recording = [m.metadata for m in metadata if m.name == RECORDING_METADATA]
    assert recording == [
        {
            "name": "run1",
            "selectors": json.dumps(["*/location", "scout1/*"]),
            "started": "2027-01-15T08:00:00Z",
            "file": "1",
            "gateway": "9.9",
        }
    ]
    services = {m.metadata["service"]: m.metadata for m in metadata if m.name == SERVICE_METADATA}
    assert set(services) == {"scout1", "scout2"}
    assert services["scout1"]["type"] == "mobile_robot"
    assert model_from_text(services["scout1"]["model"], "mobile_robot").properties == ROBOT.properties

    channels = {c.topic: c for c in summary.channels.values()}
    assert set(channels) == {
        EVENTS_TOPIC,
        "/scout1/location",
        "/scout1/battery",
        "/scout1/moving",
        "/scout1/camera",
        "/scout1/camera/image",
        "/scout1/name",
        "/scout1/pose",
        "/scout2/location",
        "/scout2/pose",
        "/scene",
    }
    schema_of = {topic: summary.schemas[c.schema_id] for topic, c in channels.items()}
    assert schema_of["/scout1/battery"].name == "propertyservice.number"
    assert schema_of["/scout1/battery"].encoding == "jsonschema"
    assert channels["/scout1/battery"].message_encoding == "json"
    assert channels["/scout1/battery"].metadata == {
        "service": "scout1",
        "property": "battery",
        "type": "number",
        "unit": "%",
    }
    assert channels["/scout1/camera"].metadata["binary"] == "true"
    for topic, name in (
        (EVENTS_TOPIC, "propertyservice.v1.Event"),
        ("/scout1/pose", "foxglove.PoseInFrame"),
        ("/scene", "foxglove.SceneUpdate"),
        ("/scout1/camera/image", "foxglove.CompressedImage"),
    ):
        assert (schema_of[topic].name, schema_of[topic].encoding) == (name, "protobuf")
        assert channels[topic].message_encoding == "protobuf"

    by_topic: dict[str, list[Message]] = {}
    for _, channel, message in messages:
        by_topic.setdefault(channel.topic, []).append(message)
    # Every change on the contract channel, in order, whatever else it feeds.
    events = [pb.Event.FromString(m.data) for m in by_topic[EVENTS_TOPIC]]
    assert [(e.service, e.property, e.sequence) for e in events] == [
        (e.service, e.path, e.sequence) for e in SOME
    ]
    assert events[3].data == b"\xff\xd8\xff\xe0jpeg" and events[3].value == ""
    assert (events[5].conflated, events[6].gap, events[7].removed) == (2, True, True)
    assert events[0].time.ToNanoseconds() == SOME[0].time_ns
    # log time: when heard by the recorder; publish time: the event's own; sequences per channel.
    assert [(m.log_time, m.publish_time) for m in by_topic[EVENTS_TOPIC]] == [
        (e.time_ns + 500, e.time_ns) for e in SOME
    ]
    assert [m.sequence for m in by_topic["/scout1/location"]] == [1, 2]

    # Every JSON message is valid against its channel's schema, its value typed by the model.
    for topic, listed in by_topic.items():
        if channels[topic].message_encoding != "json":
            continue
        schema = json.loads(schema_of[topic].data)
        for message in listed:
            jsonschema.validate(json.loads(message.data), schema)
    values = {
        topic: [json.loads(m.data)["value"] for m in listed]
        for topic, listed in by_topic.items()
        if channels[topic].message_encoding == "json"
    }
    assert values["/scout1/location"] == [[1.0, 2.0, 0.0, 0.0, 0.0, 1.5], [1.5, 2.0, 0.0, 0.0, 0.0, 1.5]]
    assert values["/scout1/moving"] == [True]
    assert values["/scout1/camera"] == ["/9j/4GpwZWc="]
    assert json.loads(by_topic["/scout1/location"][1].data)["conflated"] == 2

    pose = PoseInFrame.FromString(by_topic["/scout1/pose"][0].data)
    assert pose.frame_id == "world"
    assert (pose.pose.position.x, pose.pose.position.y) == (1.0, 2.0)
    orientation = pose.pose.orientation
    assert [orientation.x, orientation.y, orientation.z, orientation.w] == pytest.approx(
        quaternion(0, 0, 1.5)
    )
    scenes = [SceneUpdate.FromString(m.data) for m in by_topic["/scene"]]
    assert [e.id for s in scenes for e in s.entities] == ["scout1", "scout1", "scout2"]
    image = CompressedImage.FromString(by_topic["/scout1/camera/image"][0].data)
    assert (image.format, image.data) == ("jpeg", b"\xff\xd8\xff\xe0jpeg")


def test_a_service_s_metadata_stands_before_its_first_message(tmp_path: Path) -> None:
    path = tmp_path / "run1-0001.mcap"
    write_file(path, SOME)
    seen: list[str] = []
    topics: dict[int, str] = {}
    with open(path, "rb") as f:
        for record in StreamReader(f).records:
            if isinstance(record, Metadata) and record.name == SERVICE_METADATA:
                seen.append("meta " + record.metadata["service"])
            elif isinstance(record, Channel):
                topics[record.id] = record.topic
            elif isinstance(record, Message) and topics[record.channel_id] == EVENTS_TOPIC:
                service = pb.Event.FromString(record.data).service
                if f"meta {service}" not in seen:
                    seen.append(f"message of {service} before its metadata")
    assert seen == ["meta scout1", "meta scout2"]


def test_history_reads_the_events_of_every_file_oldest_first_within_its_range(tmp_path: Path) -> None:
    (tmp_path / "run1").mkdir()
    (tmp_path / "run2").mkdir()
    write_file(tmp_path / "run2" / "run2-0001.mcap", [event(n, "location", f"({n} 0)") for n in (10, 11, 12)])
    write_file(tmp_path / "run1" / "run1-0001.mcap", SOME)

    locations = events_between(tmp_path, "*", "location", None, None, 100)
    assert [(e.service, e.value) for e in locations] == [
        ("scout1", "(1 2 0 0 0 1.5)"),
        ("scout1", "(1.5 2 0 0 0 1.5)"),
        ("scout2", "(2 2 0 0 0 1.5)"),
        ("scout1", "(10 0)"),
        ("scout1", "(11 0)"),
        ("scout1", "(12 0)"),
    ]
    ranged = events_between(tmp_path, "scout1", "location", T0 + 6_000_000, T0 + 11_000_000, 100)
    assert [e.sequence for e in ranged] == [6, 10, 11]
    assert events_between(tmp_path, "scout1", "*", None, None, 2) == [
        RecordedEvent(
            "scout1", "location", "(1 2 0 0 0 1.5)", T0 + 1_000_000, T0 + 1_000_500, 1, 0, False, False
        ),
        RecordedEvent("scout1", "battery", "87.5", T0 + 2_000_000, T0 + 2_000_500, 2, 0, False, False),
    ]
    binary = events_between(tmp_path, "*", "camera", None, None, 10)
    assert [e.value for e in binary] == [b"\xff\xd8\xff\xe0jpeg"]
    assert events_between(tmp_path, "*", "*", None, None, 0) == []


def test_a_file_its_writer_never_finished_is_read_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "run1-0001.mcap"
    recording = write_file(path, SOME[:3], finish=False)
    recording.close_chunk()
    for e in SOME[3:]:
        recording.write(e, e.time_ns, INFO)  # in a chunk never closed: lost with the writer
    complete = path.stat().st_size
    with open(path, "ab") as f:
        f.write(b"\x06half a chunk")  # what a write cut off by a kill leaves
    assert [e.sequence for e in recorded_events(path)] == [1, 2, 3]
    assert path.stat().st_size > complete


def fields(e: FollowedEvent) -> EventFields:
    return tuple(e)  # type: ignore[return-value]


def _writer(tmp_path: Path, **limits: int) -> RecordingWriter:
    budget = DiskBudget(tmp_path, 1 << 30, "refuse", lambda p: None)
    return RecordingWriter(
        name="run1",
        selectors=["scout1/*"],
        folder=tmp_path,
        version="",
        limits=Limits(max_file_bytes=1 << 20, max_file_seconds=600, **limits),  # type: ignore[arg-type]
        budget=budget,
        describe=lambda service: INFO,
    )


def _feed(sent: list[tuple[Any, ...]], ended: list[RecordingFeed], **limits: int) -> RecordingFeed:
    return RecordingFeed(
        name="run1",
        selectors=["scout1/*"],
        limits=Limits(max_file_bytes=1 << 20, max_file_seconds=600, **limits),  # type: ignore[arg-type]
        started_ns=T0,
        send=sent.append,
        on_end=ended.append,
    )


def _sent_events(sent: list[tuple[Any, ...]]) -> list[EventFields]:
    return [f for message in sent if message[0] == "events" for _, group in message[2] for f in group]


async def test_a_full_intake_drops_values_counts_them_and_marks_the_next_one_a_gap() -> None:
    sent: list[tuple[Any, ...]] = []
    feed = _feed(sent, [], max_queued_events=3)
    feed.offer([event(1, "battery", "1"), event(2, "location", "(0 0)")])
    feed.offer([event(3, "battery", "2"), event(4, "moving", "true")])  # over 3: dropped
    feed.offer([event(5, "name", "a")])
    feed.flush()
    # Sent but not reported written by the writer process: still in the intake, which is full.
    feed.offer([event(6, "battery", "3")])
    assert feed.dropped == 3
    assert [f[3] for f in _sent_events(sent)] == [1, 2, 5]

    feed.progress(3, 7, {"size": 0, "messages": 6, "events": 3, "gaps": 0, "conflated": 0, "files": []})
    feed.offer([event(7, "moving", "false"), event(8, "battery", "4"), event(9, "battery", "5")])
    feed.stop()
    assert sent[-1] == ("stop", "run1")
    # The first change after a loss of each property carries gap; the next one does not.
    assert [(f[3], f[6]) for f in _sent_events(sent)[3:]] == [(7, True), (8, True), (9, False)]
    feed.offer([event(10, "battery", "6")])  # after the stop: nothing more
    assert len(_sent_events(sent)) == 6


async def test_a_batch_goes_to_the_writer_process_after_a_twentieth_of_a_second_or_when_large() -> None:
    sent: list[tuple[Any, ...]] = []
    feed = _feed(sent, [])
    feed.offer([event(1, "battery", "1")])
    feed.offer([event(2, "battery", "2")])
    assert sent == []
    await asyncio.sleep(BATCH_SECONDS * 2)
    assert [len(message[2]) for message in sent] == [2]  # one frame, the two offers' groups
    feed.offer([event(n, "battery", str(n)) for n in range(3, 3 + BATCH_EVENTS)])
    assert len(sent) == 2  # at once


async def test_a_stopped_recording_is_stopping_until_the_writer_process_has_finished_its_file() -> None:
    sent: list[tuple[Any, ...]] = []
    ended: list[RecordingFeed] = []
    feed = _feed(sent, ended)
    feed.offer([event(1, "battery", "1")])
    feed.stop()
    assert [m[0] for m in sent] == ["events", "stop"]  # what was gathered goes first
    assert (feed.state, feed.running) == ("stopping", True)
    await feed.wait(0.01)  # the process has not answered: the wait ends at its bound
    assert feed.running
    stats = {"size": 900, "messages": 2, "events": 1, "gaps": 0, "conflated": 0, "files": ["run1-0001.mcap"]}
    feed.ended("stopped", "", stats)
    await feed.wait(1.0)
    assert (feed.state, feed.running, feed.size, feed.files) == ("stopped", False, 900, ["run1-0001.mcap"])
    assert ended == [feed]


async def test_a_recording_whose_writer_process_is_gone_fails_and_says_why() -> None:
    ended: list[RecordingFeed] = []
    feed = _feed([], ended)
    feed.offer([event(1, "battery", "1")])
    feed.lost("the recorder's writer process (pid 7) ended: it was killed by SIGKILL")
    await feed.wait(1.0)
    assert (feed.state, feed.running) == ("failed: the writer process ended", False)
    assert "killed by SIGKILL" in feed.reason
    assert ended == [feed]


def test_a_full_disk_stops_the_recording_with_a_clear_state(tmp_path: Path) -> None:
    writer = _writer(tmp_path)
    writer._open_file = lambda path: open("/dev/full", "wb")  # noqa: SIM115 - every write: ENOSPC
    writer.write([(T0, [fields(event(n, "name", "x" * 10_000)) for n in range(1, 50)])])
    assert writer.ended
    assert writer.state == "failed: disk full"
    assert "no space left" in writer.reason


def test_a_recording_ends_at_its_own_size_limit_and_says_why(tmp_path: Path) -> None:
    writer = _writer(tmp_path, max_bytes=70_000)
    for n in range(1, 1000):
        writer.write([(T0, [fields(event(n, "name", os.urandom(2000).hex()))])])  # zstd cannot shrink it
        writer.tick()
        if writer.ended:
            break
    assert writer.state == "stopped"
    assert writer.reason.startswith("max_size reached")
    assert writer.size >= 70_000


def test_the_end_of_the_writer_process_s_input_finishes_every_file(tmp_path: Path) -> None:
    """The process's loop on real pipes, in this process: the recorder's messages in, then the end
    of its input, as a gateway killed leaves it; the file is complete, summary and all."""
    to_writer, from_recorder = os.pipe()
    to_recorder, from_writer = os.pipe()
    folder = tmp_path / "run1"
    folder.mkdir()
    answers = os.fdopen(to_recorder, "rb")
    out = os.fdopen(from_writer, "wb")
    process = WriterProcess(to_writer, out)
    loop = threading.Thread(target=process.run)
    loop.start()
    try:
        with os.fdopen(from_recorder, "wb") as recorder:
            recorder.write(frame(("open", str(tmp_path), 1 << 30, "refuse")))
            limits = asdict(Limits(max_file_bytes=1 << 20, max_file_seconds=600))
            recorder.write(frame(("start", "run1", ["scout1/*"], str(folder), "9.9", T0, limits)))
            recorder.write(frame(("events", "run1", [(T0, [fields(e) for e in SOME])])))
            recorder.flush()
            reader = FrameReader()
            received: list[tuple[Any, ...]] = []
            while not any(m[0] == "describe" for m in received):
                received += reader.feed(os.read(to_recorder, 65536))
            recorder.write(frame(("service", "scout1", "mobile_robot", ROBOT)))
            recorder.write(frame(("service", "scout2", "mobile_robot", ROBOT)))
            recorder.flush()
            while not any(m[0] == "progress" for m in received):
                received += reader.feed(os.read(to_recorder, 65536))
        # The end of the input: the loop finishes the file and returns.
        loop.join(10)
        assert not loop.is_alive()
        out.close()  # as the process's exit closes it
        received += reader.feed(answers.read())
    finally:
        answers.close()
    assert [m[1] for m in received if m[0] == "describe"] == ["scout1", "scout2"]
    progress = next(m for m in received if m[0] == "progress")
    assert progress[1:3] == ("run1", len(SOME))
    ended = next(m for m in received if m[0] == "ended")
    assert ended[1:3] == ("run1", "stopped")
    path = folder / "run1-0001.mcap"
    assert ended[4]["size"] == path.stat().st_size
    with open(path, "rb") as f:
        reader_ = make_reader(f)
        assert reader_.get_summary() is not None
        events = [
            pb.Event.FromString(m.data) for _, c, m in reader_.iter_messages() if c.topic == EVENTS_TOPIC
        ]
    assert [e.sequence for e in events] == [e.sequence for e in SOME]


def test_a_file_the_budget_removes_as_a_recording_ends_is_not_among_the_files_its_end_reports(
    tmp_path: Path,
) -> None:
    """Finishing the last file (its summary) can spend the budget: the oldest file of the same
    recording goes, and the ``ended`` message lists what is on disk."""
    out = io.BytesIO()
    process = WriterProcess(-1, out)
    folder = tmp_path / "run1"
    folder.mkdir()
    process._handle(("open", str(tmp_path), 1 << 30, "drop_oldest"))
    limits = asdict(Limits(max_file_bytes=20_000, max_file_seconds=600))
    process._handle(("start", "run1", ["scout1/*"], str(folder), "9.9", T0, limits))
    process._writers["run1"]._services["scout1"] = INFO  # as the recorder would answer
    for n in range(1, 30):  # several files: rotation at 20 kB
        process._handle(("events", "run1", [(T0, [fields(event(n, "name", os.urandom(1500).hex()))])]))
    assert len(list(folder.iterdir())) >= 3
    assert process._budget is not None
    process._budget.max_total_bytes = process._budget.used  # the open file's summary will not fit
    process._handle(("stop", "run1"))
    sent = FrameReader().feed(out.getvalue())
    removed = [Path(m[1]).name for m in sent if m[0] == "removed"]
    assert removed == ["run1-0001.mcap"], "the oldest went to make room for the summary"
    ended = next(m for m in sent if m[0] == "ended")
    assert ended[4]["files"] == sorted(p.name for p in folder.iterdir())


def test_frames_cut_anywhere_read_back_whole_and_an_oversized_one_is_refused() -> None:
    messages = [("events", "run1", [(T0, [fields(e) for e in SOME])]), ("stop", "run1")]
    data = b"".join(frame(m) for m in messages)
    reader = FrameReader()
    read: list[tuple[Any, ...]] = []
    for i in range(0, len(data), 7):
        read += reader.feed(data[i : i + 7])
    assert read == messages
    assert reader.pending == 0
    with pytest.raises(FrameError, match="over"):
        FrameReader().feed(b"\xff\xff\xff\xff")


def test_the_budget_removes_the_oldest_finished_files_and_never_an_open_one(tmp_path: Path) -> None:
    removed: list[Path] = []
    for i, name in enumerate(("a/a-0001.mcap", "a/a-0002.mcap", "b/b-0001.mcap")):
        path = tmp_path / name
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(b"x" * 1000)
        stamp = 1_700_000_000 + i
        os.utime(path, (stamp, stamp))
    budget = DiskBudget(tmp_path, 2500, "drop_oldest", removed.append)
    budget.scan()
    assert budget.used == 3000
    budget.opened(tmp_path / "a/a-0001.mcap")
    assert budget.grow(0)
    assert removed == [tmp_path / "a/a-0002.mcap"]  # the oldest, a-0001, is being written
    assert budget.grow(600)
    assert removed[1:] == [tmp_path / "b/b-0001.mcap"]
    assert not budget.grow(2000)  # nothing left that may go
    assert (tmp_path / "a/a-0001.mcap").exists()

    refusing = DiskBudget(tmp_path, 500, "refuse", removed.append)
    refusing.scan()
    assert refusing.full()
    assert not refusing.grow(1)
    assert (tmp_path / "a/a-0001.mcap").exists()


def test_recorded_counts_by_topic_match_what_was_written(tmp_path: Path) -> None:
    path = tmp_path / "run1-0001.mcap"
    write_file(path, SOME)
    with open(path, "rb") as f:
        counts = Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages())
    assert counts[EVENTS_TOPIC] == len(SOME)
    assert counts["/scout1/location"] == 2 and counts["/scout1/pose"] == 2 and counts["/scene"] == 3
