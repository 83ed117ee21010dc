"""Recordings written for tests, as the recorder writes them (docs/recording.md, "The file").

:func:`write_recording` writes a recording's folder (``NAME/NAME-0001.mcap`` …) with the ``mcap``
library: the ``propertyservice.recording`` and ``propertyservice.service`` metadata, a JSON channel
per property, and the ``/_events`` channel of ``propertyservice.v1.Event`` messages, with the log
and publish times the recorder gives them. :func:`swarm_recording` is the one the replay and export
tests share: two robots and a camera, with a gap and a removal among their changes.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from pathlib import Path

from google.protobuf import descriptor_pb2
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType, Writer

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.model import Access, ParameterModel, PropertyModel, ServiceModel
from services.kernel.model_codec import model_to_text
from services.kernel.values import Value

#: The recordings' first change, ns since the epoch (2026-01-02T03:04:05Z).
START_NS = 1_767_323_045_000_000_000


@dataclass(frozen=True, slots=True)
class Recorded:
    """One change as a test records it: ``at_s`` seconds after the recording's start."""

    service: str
    path: str
    value: Value
    at_s: float
    gap: bool = False
    removed: bool = False
    #: The change's own time, seconds after the start (a device's clock); None: when received.
    source_s: float | None = None

    @property
    def log_time_ns(self) -> int:
        return START_NS + round(self.at_s * 1e9)

    @property
    def time_ns(self) -> int:
        return START_NS + round((self.at_s if self.source_s is None else self.source_s) * 1e9)


def _event_schema() -> bytes:
    """The FileDescriptorSet of ``propertyservice.v1.Event`` and the files it depends on."""
    files = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(descriptor: object) -> None:
        name = descriptor.name  # type: ignore[attr-defined]
        if name in seen:
            return
        seen.add(name)
        for dependency in descriptor.dependencies:  # type: ignore[attr-defined]
            add(dependency)
        proto = descriptor_pb2.FileDescriptorProto()
        descriptor.CopyToProto(proto)  # type: ignore[attr-defined]
        files.file.append(proto)

    add(pb.Event.DESCRIPTOR.file)
    return files.SerializeToString()


def _json_schema(prop: PropertyModel) -> bytes:
    value: dict[str, object] = {"type": "string"}
    if prop.type in ("number", "integer"):
        value = {"type": "number"}
    elif prop.type == "boolean":
        value = {"type": "boolean"}
    elif prop.type == "vector":
        value = {"type": "array", "items": {"type": "number"}}
    schema = {
        "type": "object",
        "properties": {
            "value": value,
            "seq": {"type": "integer"},
            "conflated": {"type": "integer"},
            "gap": {"type": "boolean"},
            "removed": {"type": "boolean"},
        },
    }
    return json.dumps(schema).encode()


def _json_value(prop: PropertyModel | None, value: Value) -> object:
    if isinstance(value, bytes):
        return base64.b64encode(value).decode("ascii")
    if prop is not None and prop.type in ("number", "integer") and value:
        return float(value)
    if prop is not None and prop.type == "vector" and value:
        return [float(x) for x in value.strip("()").split()]
    return value


def write_recording(
    folder: Path,
    name: str,
    services: dict[str, ServiceModel],
    changes: list[Recorded],
    *,
    files: int = 1,
) -> Path:
    """Write recording ``name`` into ``folder / name`` as ``files`` files (the changes split evenly
    among them, in time order); return the recording's folder."""
    where = folder / name
    where.mkdir(parents=True, exist_ok=True)
    ordered = sorted(changes, key=lambda c: c.log_time_ns)
    per_file = -(-len(ordered) // files) if ordered else 0
    event_schema = _event_schema()
    for index in range(files):
        part = ordered[index * per_file : (index + 1) * per_file]
        with (where / f"{name}-{index + 1:04d}.mcap").open("wb") as stream:
            writer = Writer(stream, compression=CompressionType.ZSTD)
            writer.start(profile="", library="psgateway recorder test")
            writer.add_metadata(
                "propertyservice.recording",
                {
                    "name": name,
                    "selectors": json.dumps(["*/*"]),
                    "started": "2026-01-02T03:04:05Z",
                    "file": str(index + 1),
                    "gateway": "test",
                },
            )
            events_schema = writer.register_schema("propertyservice.v1.Event", "protobuf", event_schema)
            events = writer.register_channel("/_events", "protobuf", events_schema)
            described: set[str] = set()
            channels: dict[tuple[str, str], int] = {}
            sequences: dict[int, int] = {}
            for change in part:
                model = services[change.service]
                if change.service not in described:
                    described.add(change.service)
                    writer.add_metadata(
                        "propertyservice.service",
                        {"service": change.service, "type": model.type, "model": model_to_text(model)},
                    )
                prop = next((p for p in model.properties if p.name == change.path), None)
                key = (change.service, change.path)
                if key not in channels:
                    kind = prop.type if prop is not None else "unknown"
                    schema = writer.register_schema(
                        f"propertyservice.{kind}",
                        "jsonschema",
                        _json_schema(prop or PropertyModel(change.path, "text", Access.READ)),
                    )
                    metadata = {
                        "service": change.service,
                        "property": change.path,
                        "type": kind,
                        "unit": prop.unit if prop else "",
                    }
                    if isinstance(change.value, bytes):
                        metadata["binary"] = "true"
                    channels[key] = writer.register_channel(
                        f"/{change.service}/{change.path.replace('.', '/')}", "json", schema, metadata
                    )
                for channel in (channels[key], events):
                    sequences[channel] = sequences.get(channel, 0) + 1
                stamp = Timestamp()
                stamp.FromNanoseconds(change.time_ns)
                event = pb.Event(
                    service=change.service,
                    property=change.path,
                    sequence=sequences[events],
                    time=stamp,
                    gap=change.gap,
                    removed=change.removed,
                )
                if isinstance(change.value, bytes):
                    event.data = change.value
                else:
                    event.value = change.value
                body = {
                    "value": _json_value(prop, change.value),
                    "seq": sequences[channels[key]],
                    "conflated": 0,
                    "gap": change.gap,
                    "removed": change.removed,
                }
                writer.add_message(
                    channels[key],
                    change.log_time_ns,
                    json.dumps(body).encode(),
                    change.time_ns,
                    sequences[channels[key]],
                )
                writer.add_message(
                    events, change.log_time_ns, event.SerializeToString(), change.time_ns, sequences[events]
                )
            writer.finish()  # type: ignore[no-untyped-call]
    return where


ROBOT = ServiceModel(
    type="mobile_robot",
    properties=(
        PropertyModel(
            "location",
            "vector",
            Access.READ,
            length=6,
            unit="m, rad",
            gui="pose",
            doc="x y z roll pitch yaw, world frame",
        ),
        PropertyModel(
            "speed",
            "number",
            Access.READ_WRITE,
            unit="m/s",
            minimum=0.0,
            maximum=5.0,
            gui="slider",
            doc="cruise speed of moveto",
        ),
        PropertyModel("sensors.battery", "number", Access.READ, unit="1", doc="charge"),
        PropertyModel("status", "text", Access.READ, doc="what the robot does"),
        PropertyModel(
            "behaviors.moveto",
            "none",
            Access.ACTION,
            doc="drive to a marker",
            value=ParameterModel("target", "marker"),
        ),
    ),
)
CAMERA = ServiceModel(
    type="camera",
    properties=(
        PropertyModel("frame", "bytes", Access.READ, media_type="image/png", doc="the latest frame"),
    ),
)

#: Bytes that stand for a PNG frame (the export and replay carry them untouched).
FRAME_A = b"\x89PNG\r\n\x1a\nframe-a" + bytes(range(256))
FRAME_B = b"\x89PNG\r\n\x1a\nframe-b" + bytes(reversed(range(256)))


def swarm_changes() -> list[Recorded]:
    """Two robots driving for 4 s and a camera: numbers, text, vectors, binary frames, a gap and a removal."""
    changes = [
        Recorded("scout1", "location", "(0 0 0 0 0 0)", 0.0),
        Recorded("scout1", "speed", "0.5", 0.0),
        Recorded("scout1", "sensors.battery", "1", 0.0),
        Recorded("scout1", "status", "idle", 0.0),
        Recorded("scout2", "location", "(5 5 0 0 0 3.14159)", 0.0),
        Recorded("scout2", "speed", "0.8", 0.0),
        Recorded("scout2", "sensors.battery", "0.9", 0.0),
        Recorded("scout2", "status", "idle", 0.0),
        Recorded("cam1", "frame", FRAME_A, 0.0),
    ]
    for step in range(1, 9):
        t = step * 0.5
        changes.append(
            Recorded(
                "scout1", "location", f"({step * 0.5:g} {step * 0.25:g} 0 0 0 0.5)", t, source_s=t - 0.01
            )
        )
        changes.append(Recorded("scout2", "location", f"({5 - step * 0.5:g} 5 0 0 0.1 3)", t + 0.05))
        changes.append(Recorded("scout1", "sensors.battery", f"{1 - step * 0.01:g}", t + 0.1))
    changes += [
        Recorded("scout1", "status", "driving", 0.4),
        Recorded("scout2", "status", "driving", 1.2),
        Recorded("cam1", "frame", FRAME_B, 2.0),
        # The robot's link broke and came back: values may have been lost before this one.
        Recorded("scout2", "sensors.battery", "0.7", 2.6, gap=True),
        Recorded("scout1", "speed", "1.5", 3.0),
        Recorded("scout2", "status", "", 3.5, removed=True),
        Recorded("scout1", "status", "arrived", 4.0),
    ]
    return changes


SWARM_SERVICES = {"scout1": ROBOT, "scout2": ROBOT, "cam1": CAMERA}


def swarm_recording(folder: Path, name: str = "swarm", files: int = 2) -> Path:
    """The test swarm's recording in ``folder / name``, cut into ``files`` files."""
    return write_recording(folder, name, SWARM_SERVICES, swarm_changes(), files=files)
