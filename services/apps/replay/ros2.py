"""A recording exported as a ROS 2 bag (MCAP storage), for ``ros2 bag play`` and ROS tools.

Every recorded change (the ``/_events`` channel) becomes one message on the topic the rosbridge
front names the property by (:func:`services.kernel.ros_names.ros_name`: ``/scout1/sensors/battery``),
of the type the rosbridge front gives it (:func:`services.kernel.ros_messages.default_type`: a number
``std_msgs/msg/Float64``, text ``std_msgs/msg/String``, a vector ``std_msgs/msg/Float64MultiArray``,
a binary image ``sensor_msgs/msg/CompressedImage``, …), but for a ``location``, which is a
``geometry_msgs/msg/PoseStamped`` in the ``world`` frame. The message's time in the bag is the
change's log time (when the gateway received it); a stamped message's header carries the change's
own time. A removal has no message (ROS has no word for it), and a value that does not read as its
type (a device that sent a bad one) is left out; :class:`ExportReport` counts both.

The bag is written by ``rosbags`` (pure Python, no ROS install needed) with its MCAP storage plugin.
"""

from __future__ import annotations

import base64
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from services.apps.replay.recording import RecordedEvent, Recording
from services.kernel import ros_messages
from services.kernel.errors import InvalidArgument
from services.kernel.model import Access, PropertyModel
from services.kernel.ros_names import ros_name

__all__ = ["ExportReport", "export_ros2", "message_type"]

#: The message definitions the bag is written with: ROS 2 Humble's (the long-term release; the
#: std_msgs, geometry_msgs and sensor_msgs used here are the same in every ROS 2 release since).
STORE = Stores.ROS2_HUMBLE
#: The bag format version rosbags writes (9: what ROS 2 Jazzy's rosbag2 reads and writes).
BAG_VERSION: Literal[8, 9] = 9

#: Unreadable values the report names (it counts them all).
MAX_REPORTED = 20
#: Told (changes done, changes in all) as the export goes.
Progress = Callable[[int, int], None]


@dataclass
class ExportReport:
    """What an export wrote and what it left out."""

    #: Messages written, by topic.
    messages: dict[str, int] = field(default_factory=dict)
    #: Topic → its message type (ROS 2's ``pkg/msg/Name``).
    types: dict[str, str] = field(default_factory=dict)
    #: Removals, which have no message.
    removals: int = 0
    #: Values that did not read as their type (left out): (topic, why), the first :data:`MAX_REPORTED`.
    unreadable: list[tuple[str, str]] = field(default_factory=list)
    unreadable_count: int = 0

    @property
    def written(self) -> int:
        return sum(self.messages.values())


def _ros2(type_name: str) -> str:
    """``std_msgs/Float64`` as ROS 2 spells it: ``std_msgs/msg/Float64``."""
    package, _, name = type_name.partition("/")
    return f"{package}/msg/{name}"


def message_type(prop: PropertyModel | None, value: object) -> str:
    """The ROS message type (rosbridge's spelling) a property's changes are exported as."""
    if prop is None:
        prop = PropertyModel("", "bytes" if isinstance(value, bytes) else "text", Access.UNKNOWN)
    if prop.type == "vector" and (prop.name == "location" or prop.name.endswith(".location")):
        return ros_messages.POSE_STAMPED
    return ros_messages.default_type(prop)


def _built(store: Typestore, type_name: str, fields: Mapping[str, Any]) -> Any:
    """The rosbags message of ``type_name`` from the rosbridge message ``fields`` (JSON's shape:
    nested objects, lists of numbers, ``uint8[]`` as base64 text). Fields the type has not (ROS 1's
    ``secs`` beside ROS 2's ``sec``) are ignored; missing ones are an error."""
    _consts, defs = store.fielddefs[type_name]
    values: dict[str, Any] = {}
    for name, (node, spec) in defs:
        # The definition's shape depends on the node kind (rosbags' Nodetype): read it as such.
        detail: Any = spec
        given = fields[name]
        kind = node.name
        if kind == "NAME":
            values[name] = _built(store, detail, given)
        elif kind in ("SEQUENCE", "ARRAY"):
            (element_node, element), _size = detail
            if element_node.name == "NAME":
                values[name] = [_built(store, element, item) for item in given]
            else:
                base = element[0]
                if base == "string":
                    values[name] = list(given)
                elif isinstance(given, str):  # uint8[] travels as base64 text, as rosbridge writes it
                    given = base64.b64decode(given)
                    values[name] = np.frombuffer(given, dtype=np.uint8).copy()
                else:
                    values[name] = np.asarray(given, dtype=np.dtype(base))
        else:
            values[name] = given
    return store.types[type_name](**values)


def export_ros2(recording: Recording, out_dir: Path, *, progress: Progress | None = None) -> ExportReport:
    """Write ``recording`` as a ROS 2 bag into ``out_dir`` (which must not exist yet)."""
    if out_dir.exists():
        raise InvalidArgument(f"{out_dir} exists already: name a new folder for the bag")
    if not out_dir.parent.is_dir():
        raise InvalidArgument(f"{out_dir.parent} is no folder: the bag's folder goes into an existing one")
    store = get_typestore(STORE)
    models = {
        name: {p.name: p for p in service.model.properties} for name, service in recording.services.items()
    }
    total = recording.event_count
    exporter = _Exporter(store, models)
    with Writer(out_dir, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
        for done, event in enumerate(recording.events(), start=1):
            if progress is not None:
                progress(done, total)
            exporter.write(writer, event)
    return exporter.report


class _Exporter:
    """Writes changes into a bag: one connection a topic, its type fixed by its first message."""

    def __init__(self, store: Typestore, models: Mapping[str, Mapping[str, PropertyModel]]) -> None:
        self.store = store
        self.models = models
        self.report = ExportReport()
        self.connections: dict[str, Any] = {}

    def write(self, writer: Writer, event: RecordedEvent) -> None:
        report = self.report
        if event.removed:
            report.removals += 1
            return
        topic = ros_name(event.service, event.path)
        prop = self.models.get(event.service, {}).get(event.path)
        type_name = report.types.get(topic) or _ros2(message_type(prop, event.value))
        try:
            fields = ros_messages.to_message(
                ros_messages.canonical(type_name),
                event.value,
                stamp_ns=event.time_ns,
                media_type=prop.media_type if prop is not None else "",
            )
            data = self.store.serialize_cdr(_built(self.store, type_name, fields), type_name)
        except (InvalidArgument, ValueError) as exc:
            report.unreadable_count += 1
            if len(report.unreadable) < MAX_REPORTED:
                why = exc.message if isinstance(exc, InvalidArgument) else str(exc)
                report.unreadable.append((topic, why))
            return
        connection = self.connections.get(topic)
        if connection is None:
            connection = self.connections[topic] = writer.add_connection(
                topic, type_name, typestore=self.store
            )
            report.types[topic] = type_name
        writer.write(connection, event.log_time_ns, bytes(data))
        report.messages[topic] = report.messages.get(topic, 0) + 1


class ProgressLine:
    """Progress of an export: ``exported N of M changes (P%)``, on a terminal one line rewritten
    twice a second, elsewhere (a log) a line every 5 s."""

    def __init__(self, write: Callable[[str], object], *, terminal: bool) -> None:
        self._write = write
        self._terminal = terminal
        self._period_s = 0.5 if terminal else 5.0
        self._next = time.monotonic() + (0.0 if terminal else self._period_s)

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if now < self._next and not (self._terminal and done == total):
            return
        self._next = now + self._period_s
        share = f" ({100 * done // total}%)" if total else ""
        line = f"exported {done} of {total} changes{share}"
        self._write(f"\r{line}" if self._terminal else f"{line}\n")
