"""One recording file: the MCAP layout that Foxglove, ROS tools and the gateway's own readers share.

A recording ``NAME`` is ``NAME-0001.mcap``, ``NAME-0002.mcap`` … in its own folder (a file
ends and the next begins at the size or duration limit). Each file is written with the
``mcap`` library's :class:`mcap.writer.Writer`, chunked and zstd-compressed, and holds:

* a metadata record ``propertyservice.recording``: ``name``, ``selectors`` (a JSON list),
  ``started`` (ISO 8601 UTC), ``file`` (its index, "1", "2" …) and ``gateway`` (the version);
* before a service's first message in the file, a metadata record ``propertyservice.service``:
  ``service``, ``type`` and ``model`` (:func:`services.kernel.model_codec.model_to_text`);
* per (service, property) a JSON channel ``/<service>/<path, dots as slashes>`` (the Foxglove
  and rosbridge fronts' topic), schema ``propertyservice.<type>`` in ``jsonschema``: messages
  ``{"value", "seq", "conflated", "gap", "removed"}`` with ``value`` typed by the model
  (:mod:`services.kernel.typed`; a binary value as base64, channel metadata ``binary = "true"``);
* the well-known channels Foxglove's panels draw with no set-up (protobuf, the schemas of
  ``foxglove-schemas-protobuf`` as FileDescriptorSets): ``/<service>/pose``
  (``foxglove.PoseInFrame``) and ``/scene`` (``foxglove.SceneUpdate``, one entity per service)
  for every ``location``, ``/<service>/<path>/image`` (``foxglove.CompressedImage``) for a binary
  ``image/*`` property;
* ``/_events``: every change as the contract's ``propertyservice.v1.Event`` (protobuf), which
  replay and history read (:mod:`services.apps.recorder.reading`).

A message's ``log_time`` is when the recorder heard the change, its ``publish_time`` the event's
own time, its ``sequence`` counts the messages of its channel in the file.

A chunk is closed (and the file flushed to the OS) at least every :data:`CHUNK_SECONDS`, so a
gateway killed mid-recording leaves every closed chunk readable (an MCAP reader that reads
without the summary: ``mcap.reader.make_reader(f)`` falls back to streaming it, or the stream
reader directly).
"""

from __future__ import annotations

import base64
import json
import math
import time
from datetime import UTC, datetime
from typing import IO, Any

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor
from google.protobuf.message import Message
from mcap.writer import CompressionType, Writer

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.follow import FollowedEvent
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.model_codec import model_to_text
from services.kernel.typed import LOCATION, WORLD_FRAME, is_image, is_pose, pose_of, typed, value_json_schema
from services.kernel.values import Value

__all__ = [
    "CHUNK_BYTES",
    "CHUNK_SECONDS",
    "EVENTS_TOPIC",
    "RECORDING_METADATA",
    "SCENE_TOPIC",
    "SERVICE_METADATA",
    "RecordingFile",
    "ServiceInfo",
    "file_name",
    "topic_of",
]

#: The contract channel: every change as a ``propertyservice.v1.Event``.
EVENTS_TOPIC = "/_events"
SCENE_TOPIC = "/scene"
RECORDING_METADATA = "propertyservice.recording"
SERVICE_METADATA = "propertyservice.service"
#: A chunk closes at this many bytes (before compression), or after CHUNK_SECONDS, whichever is
#: first: small chunks lose little when the gateway is killed, and a reader seeks in them quickly.
CHUNK_BYTES = 256 * 1024
#: A chunk is closed and flushed at least this often: what a killed gateway can lose at most.
CHUNK_SECONDS = 1.0

#: The mcap Writer's own (private) method that closes the chunk being built; the recorder's
#: unit tests fail at once should a release of the library rename it.
_FINALIZE_CHUNK = "_Writer__finalize_chunk"
_PROTOBUF = "protobuf"
_COMPACT = (",", ":")
_JSON_BOOL = {False: "false", True: "true"}
_JSON = "json"


def topic_of(service: str, path: str) -> str:
    """The topic of a property: ``/<service>/<path with dots as slashes>`` (as the fronts name it)."""
    return f"/{service}/{path.replace('.', '/')}"


def file_name(name: str, index: int) -> str:
    """The name of the recording's file number ``index`` (from 1): ``NAME-0001.mcap``."""
    return f"{name}-{index:04d}.mcap"


def _descriptor_set(descriptor: Any) -> bytes:
    """The FileDescriptorSet of a message type and every file it depends on (as
    ``mcap-protobuf-support`` writes a protobuf schema), dependencies first."""
    files = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(file: FileDescriptor) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dependency in file.dependencies:
            add(dependency)
        proto = files.file.add()
        file.CopyToProto(proto)

    add(descriptor.file)
    return files.SerializeToString()


_PROTO_SCHEMAS: dict[str, bytes] = {}


def _proto_schema(message: type[Message]) -> tuple[str, bytes]:
    descriptor = message.DESCRIPTOR
    data = _PROTO_SCHEMAS.get(descriptor.full_name)
    if data is None:
        data = _PROTO_SCHEMAS[descriptor.full_name] = _descriptor_set(descriptor)
    return descriptor.full_name, data


def _json_schema(model: PropertyModel) -> dict[str, Any]:
    """The schema of a property's JSON channel: the value typed by the model, and the event's flags."""
    value = (
        {"type": "string", "contentEncoding": "base64"} if model.type == "bytes" else value_json_schema(model)
    )
    return {
        "title": f"propertyservice.{model.type}",
        "type": "object",
        "properties": {
            "value": value,
            "seq": {"type": "integer", "minimum": 0},
            "conflated": {"type": "integer", "minimum": 0},
            "gap": {"type": "boolean"},
            "removed": {"type": "boolean"},
        },
        "required": ["value", "seq", "conflated", "gap", "removed"],
    }


def _timestamp(message: Any, time_ns: int) -> None:
    message.seconds, message.nanos = divmod(time_ns, 1_000_000_000)


def _set_pose(pose: Any, position: list[float], orientation: list[float]) -> None:
    pose.position.x, pose.position.y, pose.position.z = position
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = orientation


class ServiceInfo:
    """What a recording knows of a recorded service: its type and model (None: not known)."""

    __slots__ = ("_by_name", "model", "type")

    def __init__(self, service_type: str, model: ServiceModel | None) -> None:
        self.type = service_type
        self.model = model
        self._by_name = {p.name: p for p in model.properties} if model is not None else {}

    def property(self, path: str, value: bytes | str) -> PropertyModel:
        """The model of ``path``; one of type ``bytes`` or ``text`` (by the value) when the
        service's model does not name it (a property that came later, a model not read)."""
        found = self._by_name.get(path)
        if found is None:
            kind = "bytes" if isinstance(value, bytes) else "text"
            found = self._by_name[path] = PropertyModel(name=path, type=kind, access=Access.READ)
        return found


class _Channel:
    """One channel of the file: its id, the model of what it carries, its messages so far."""

    __slots__ = ("id", "image", "model", "pose", "sequence")

    def __init__(self, channel_id: int, model: PropertyModel) -> None:
        self.id = channel_id
        self.model = model
        self.sequence = 0
        #: A location's channel (it feeds a pose and the scene), a binary image's (it feeds an image).
        self.pose = is_pose(model)
        self.image = is_image(model)


class RecordingFile:
    """One MCAP file of a recording being written; see the module docstring. Not thread-safe: one
    writer (in the writer process) owns it."""

    def __init__(
        self,
        stream: IO[bytes],
        *,
        name: str,
        selectors: list[str],
        started_ns: int,
        index: int,
        version: str,
        chunk_bytes: int = CHUNK_BYTES,
        clock: Any = time.monotonic,
    ) -> None:
        self._stream = stream
        self._clock = clock
        self._writer = Writer(stream, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"psgateway recorder {version}".strip())
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], _Channel] = {}
        #: Each property's own channel by (service, path), once its first change is written.
        self._targets: dict[tuple[str, str], _Channel] = {}
        self._events: _Channel | None = None
        self._services: set[str] = set()
        self._chunk_opened = clock()
        self._pending = False
        started = datetime.fromtimestamp(started_ns / 1e9, UTC).isoformat().replace("+00:00", "Z")
        self._writer.add_metadata(
            RECORDING_METADATA,
            {
                "name": name,
                "selectors": json.dumps(selectors),
                "started": started,
                "file": str(index),
                "gateway": version,
            },
        )
        #: Messages written to this file.
        self.messages = 0

    # -- the records -------------------------------------------------------------------

    def _schema(self, name: str, encoding: str, data: bytes) -> int:
        key = f"{encoding}:{name}:{hash(data)}"
        found = self._schemas.get(key)
        if found is None:
            found = self._schemas[key] = self._writer.register_schema(name, encoding, data)
        return found

    def _proto_channel(self, topic: str, message: type[Message]) -> _Channel:
        key = ("", topic)
        channel = self._channels.get(key)
        if channel is None:
            name, data = _proto_schema(message)
            schema = self._schema(name, _PROTOBUF, data)
            channel_id = self._writer.register_channel(topic, _PROTOBUF, schema)
            channel = self._channels[key] = _Channel(channel_id, PropertyModel(topic, "bytes", Access.READ))
        return channel

    def _value_channel(self, service: str, model: PropertyModel) -> _Channel:
        key = (service, model.name)
        channel = self._channels.get(key)
        if channel is None:
            schema = _json_schema(model)
            schema_id = self._schema(schema["title"], "jsonschema", json.dumps(schema).encode())
            metadata = {"service": service, "property": model.name, "type": model.type, "unit": model.unit}
            if model.type == "bytes":
                metadata["binary"] = "true"
                if model.media_type:
                    metadata["media_type"] = model.media_type
            channel_id = self._writer.register_channel(
                topic_of(service, model.name), _JSON, schema_id, metadata
            )
            channel = self._channels[key] = _Channel(channel_id, model)
        return channel

    def _add(self, channel: _Channel, log_ns: int, publish_ns: int, data: bytes) -> None:
        channel.sequence += 1
        self._writer.add_message(channel.id, log_ns, data, publish_ns, channel.sequence)
        self.messages += 1
        self._pending = True

    def has_service(self, service: str) -> bool:
        return service in self._services

    def add_service(self, service: str, info: ServiceInfo) -> None:
        """The service's metadata record: written before its first message in this file."""
        # The metadata record goes straight to the file: the chunk open now (earlier messages) is
        # closed first, so that the record stands before the service's messages.
        self.close_chunk()
        model = model_to_text(info.model) if info.model is not None else ""
        self._writer.add_metadata(SERVICE_METADATA, {"service": service, "type": info.type, "model": model})
        self._services.add(service)

    def _target(self, service: str, path: str, value: Value, info: ServiceInfo) -> _Channel:
        """The property's own channel (made on its first change in the file)."""
        channel = self._targets.get((service, path))
        if channel is None:
            channel = self._targets[service, path] = self._value_channel(service, info.property(path, value))
        return channel

    def write(self, event: FollowedEvent, log_ns: int, info: ServiceInfo, extra_gap: bool = False) -> None:
        """One change on its channels (its own, ``/_events``, and the well-known ones it feeds)."""
        value = event.value
        gap = event.gap or extra_gap
        publish_ns = event.time_ns or log_ns
        channel = self._target(event.service, event.path, value, info)
        model = channel.model
        record = pb.Event(
            service=event.service,
            property=event.path,
            sequence=event.sequence,
            conflated=event.conflated,
            gap=gap,
            removed=event.removed,
        )
        _timestamp(record.time, event.time_ns)
        if isinstance(value, bytes):
            record.data = value
        else:
            record.value = value
        events = self._events or self._proto_channel(EVENTS_TOPIC, pb.Event)
        self._events = events
        self._add(events, log_ns, publish_ns, record.SerializeToString())

        if event.removed:
            shown: Any = _empty_of(model)
        elif isinstance(value, bytes):
            shown = base64.b64encode(value).decode("ascii")
        else:
            shown = typed(model.type, value)
            if isinstance(shown, float) and not math.isfinite(shown):
                shown = value  # NaN and infinities are no JSON numbers: the value's text
        # The flags written out by hand: one json.dumps (of the value) a change, not of a dict.
        message = (
            f'{{"value":{json.dumps(shown, separators=_COMPACT)},"seq":{event.sequence},'
            f'"conflated":{event.conflated},"gap":{_JSON_BOOL[gap]},"removed":{_JSON_BOOL[event.removed]}}}'
        )
        self._add(channel, log_ns, publish_ns, message.encode())

        if channel.pose:
            if event.removed:
                if event.path == LOCATION:
                    self._scene(event.service, None, log_ns, publish_ns)
                return
            pose = pose_of(value) if isinstance(value, str) else None
            if pose is not None:
                if event.path == LOCATION:
                    self._scene(event.service, pose, log_ns, publish_ns)
                stamped = PoseInFrame(frame_id=WORLD_FRAME)
                _timestamp(stamped.timestamp, publish_ns)
                _set_pose(stamped.pose, *pose)
                prefix = event.path.rpartition(".")[0]
                topic = topic_of(event.service, f"{prefix}.pose" if prefix else "pose")
                self._add(
                    self._proto_channel(topic, PoseInFrame), log_ns, publish_ns, stamped.SerializeToString()
                )
        elif channel.image and isinstance(value, bytes) and not event.removed:
            image = CompressedImage(
                frame_id=event.service, data=value, format=model.media_type.partition("/")[2]
            )
            _timestamp(image.timestamp, publish_ns)
            topic = topic_of(event.service, event.path) + "/image"
            self._add(
                self._proto_channel(topic, CompressedImage), log_ns, publish_ns, image.SerializeToString()
            )

    def _scene(
        self, service: str, pose: tuple[list[float], list[float]] | None, log_ns: int, publish_ns: int
    ) -> None:
        """One service's entity on ``/scene``: an arrow where it stands and heads, its name above it;
        deleted when its location went."""
        update = SceneUpdate()
        if pose is None:
            deletion = update.deletions.add(id=service)
            _timestamp(deletion.timestamp, publish_ns)
        else:
            position, orientation = pose
            entity = update.entities.add(id=service, frame_id=WORLD_FRAME)
            _timestamp(entity.timestamp, publish_ns)
            arrow = entity.arrows.add(
                shaft_length=0.3, shaft_diameter=0.08, head_length=0.15, head_diameter=0.18
            )
            _set_pose(arrow.pose, position, orientation)
            arrow.color.r, arrow.color.g, arrow.color.b, arrow.color.a = 0.2, 0.6, 1.0, 1.0
            text = entity.texts.add(billboard=True, font_size=14, scale_invariant=True, text=service)
            _set_pose(text.pose, [position[0], position[1], position[2] + 0.4], [0.0, 0.0, 0.0, 1.0])
            text.color.r, text.color.g, text.color.b, text.color.a = 1.0, 1.0, 1.0, 1.0
        self._add(
            self._proto_channel(SCENE_TOPIC, SceneUpdate), log_ns, publish_ns, update.SerializeToString()
        )

    # -- chunks and the end ------------------------------------------------------------

    def close_chunk(self) -> None:
        """Close the chunk being built (if it holds anything) and hand the file's bytes to the OS."""
        if self._pending:
            # The library closes a chunk only when it is full or the file ends; a recording must
            # not lose more than a second when the gateway is killed. Its one method that does it:
            getattr(self._writer, _FINALIZE_CHUNK)()
            self._pending = False
        self._stream.flush()
        self._chunk_opened = self._clock()

    def tick(self) -> None:
        """Close the chunk when it has been open :data:`CHUNK_SECONDS`."""
        if self._clock() - self._chunk_opened >= CHUNK_SECONDS:
            self.close_chunk()

    @property
    def size(self) -> int:
        """Bytes in the file so far (the chunk being built not counted until it is closed)."""
        return self._stream.tell()

    def finish(self) -> None:
        """Write the summary and the footer (the file is complete and indexed) and flush it."""
        self._writer.finish()  # type: ignore[no-untyped-call]
        self._stream.flush()


def _empty_of(model: PropertyModel) -> Any:
    """The JSON value of a removed property: what its schema admits, carrying nothing."""
    if model.type in ("number", "integer"):
        return 0
    if model.type == "boolean":
        return False
    if model.type == "vector":
        return [0.0] * (model.length or 0)
    return ""
