"""The channels, services and parameters one Foxglove connection is shown, from the models.

Topics name properties as ROS names them: ``/<service>/<path with dots as slashes>``
(``/scout1/location``, ``/scout1/sensors/battery``). From each service's model:

* every property a Listen can follow is a **channel** of its own (:func:`schemas.value_schema`);
* a ``location`` vector is also ``/<service>/pose`` (``foxglove.PoseInFrame``), and every
  location together is ``/scene`` (``foxglove.SceneUpdate``);
* every action and query is a **service** (``/scout1/behaviors/moveto``), called with
  ``{"value": TEXT, "parameters": {NAME: TEXT}}`` and answering ``{"value": TEXT}``;
* every read-write number, integer, boolean or text is a **parameter** of the topic's name.

Ids are given once per topic and schema in the process, and what two connections are shown alike
is one object (an idle connection holds references, not copies). Pure but for those shared
tables: the connection describes the services and hands the models in.
"""

from __future__ import annotations

import enum
import functools
import itertools
import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from gateway.fronts.foxglove import schemas
from gateway.fronts.foxglove.protocol import JSON_ENCODING, SCHEMA_ENCODING
from services.kernel.model import Access, PropertyModel, ServiceModel

#: The topic of the scene of every location.
SCENE_TOPIC = "/scene"
#: The most channels one connection is shown: each is a line of the advertisement and, once
#: subscribed, a Listen stream; a registry bigger than this is shown in part, and says so.
MAX_CHANNELS = 4096
#: The most properties (channels, services and parameters together) one connection is shown:
#: a registry of 10,000 services describes 13 properties for each, and a connection's tables
#: must stay small whatever the gateway serves.
MAX_PROPERTIES = 4 * MAX_CHANNELS
#: Types a parameter may have: what Foxglove's parameter panel edits as a scalar.
PARAMETER_TYPES = frozenset({"number", "integer", "boolean", "text"})


class Kind(enum.Enum):
    """What a channel's messages are made from."""

    VALUE = "value"
    POSE = "pose"
    SCENE = "scene"
    #: A parameter's updates (``subscribeParameterUpdates``): ``parameterValues`` messages.
    PARAMETER = "parameter"


def _compact(schema: dict[str, Any]) -> str:
    return json.dumps(schema, separators=(",", ":"))


POSE_SCHEMA_TEXT = _compact(schemas.POSE_SCHEMA)
SCENE_SCHEMA_TEXT = _compact(schemas.SCENE_SCHEMA)


@functools.lru_cache(maxsize=MAX_CHANNELS)
def value_schema_text(prop: PropertyModel, service: str) -> str:
    """A property's schema as text, made once for every connection that is shown it (an idle
    connection holds references, not copies)."""
    return _compact(schemas.value_schema(prop, service))


@functools.lru_cache(maxsize=4 * MAX_CHANNELS)
def shared(prop: PropertyModel) -> PropertyModel:
    """The one instance of a model equal to ``prop`` that connections keep: each connection
    describes the services afresh, and would otherwise hold its own copy of every model."""
    return prop


@functools.lru_cache(maxsize=4 * MAX_CHANNELS)
def topic_of(service: str, path: str) -> str:
    return f"/{service}/{path.replace('.', '/')}"


@dataclass(frozen=True, slots=True)
class Channel:
    id: int
    topic: str
    kind: Kind
    #: The service and path it listens to (``*`` and ``location`` for the scene).
    service: str
    path: str
    model: PropertyModel | None
    schema_name: str
    #: The JSON schema as text: one string shared by every connection shown the same model.
    schema: str

    def advertised(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": JSON_ENCODING,
            "schemaName": self.schema_name,
            "schema": self.schema,
            "schemaEncoding": SCHEMA_ENCODING,
        }


@dataclass(frozen=True, slots=True)
class Service:
    """An action or a query, called as a Foxglove service."""

    id: int
    name: str
    service: str
    path: str
    model: PropertyModel

    @property
    def is_query(self) -> bool:
        return self.model.access is Access.QUERY

    def advertised(self) -> dict[str, Any]:
        value: dict[str, Any] = {"type": "string"}
        if self.model.value is not None and self.model.value.doc:
            value["description"] = self.model.value.doc
        parameters = {
            p.name: {"type": "string", "description": p.doc or p.type} for p in self.model.parameters
        }
        request = {
            "type": "object",
            "properties": {"value": value, "parameters": {"type": "object", "properties": parameters}},
        }
        response = {"type": "object", "properties": {"value": {"type": "string"}}}
        kind = "Query" if self.is_query else "Action"
        request_text = json.dumps(request, separators=(",", ":"))
        response_text = json.dumps(response, separators=(",", ":"))
        return {
            "id": self.id,
            "name": self.name,
            "type": f"propertyservice/{kind}",
            # The spec's first form (a schema text each) and its later one (encoding and schema).
            "requestSchema": request_text,
            "responseSchema": response_text,
            "request": {
                "encoding": JSON_ENCODING,
                "schemaName": f"propertyservice/{kind}Request",
                "schemaEncoding": SCHEMA_ENCODING,
                "schema": request_text,
            },
            "response": {
                "encoding": JSON_ENCODING,
                "schemaName": f"propertyservice/{kind}Response",
                "schemaEncoding": SCHEMA_ENCODING,
                "schema": response_text,
            },
        }


#: Ids of channels and services, given once per (topic, schema) in the whole process: equal
#: channels of two connections are one object, with one id (the spec lets a channel that
#: reappears the same keep its id).
_channel_ids = itertools.count(1)
_service_ids = itertools.count(1)


#: What makes a channel, but its id: topic, kind, service, path, model, schema name, schema.
ChannelSpec = tuple[str, Kind, str, str, PropertyModel | None, str, str]


@functools.lru_cache(maxsize=4 * MAX_CHANNELS)
def shared_channel(spec: ChannelSpec) -> Channel:
    return Channel(next(_channel_ids), *spec)


@functools.lru_cache(maxsize=4 * MAX_CHANNELS)
def shared_service(name: str, service: str, path: str, prop: PropertyModel) -> Service:
    return Service(next(_service_ids), name, service, path, prop)


@functools.lru_cache(maxsize=4 * MAX_CHANNELS)
def shared_property(service: str, path: str, prop: PropertyModel) -> tuple[str, str, PropertyModel]:
    return service, path, prop


@dataclass(slots=True)
class Catalog:
    """What one connection is shown; :meth:`add` a service's model at a time."""

    channels: dict[int, Channel] = field(default_factory=dict)
    services: dict[int, Service] = field(default_factory=dict)
    #: Topic → (service, path, model) of every property, for publishing and parameters.
    properties: dict[str, tuple[str, str, PropertyModel]] = field(default_factory=dict)
    #: Whether :data:`MAX_CHANNELS` cut the catalog short.
    clipped: bool = False

    def _channel(self, *args: Any) -> Channel | None:  # the fields of a ChannelSpec
        if len(self.channels) >= MAX_CHANNELS:
            self.clipped = True
            return None
        channel = shared_channel(args)
        self.channels[channel.id] = channel
        return channel

    def add(self, service: str, model: ServiceModel, may_read: Iterable[str] | None = None) -> None:
        """Show ``service``'s properties (only the paths in ``may_read`` when given)."""
        readable = None if may_read is None else set(may_read)
        for described in model.properties:
            if described.type == "namespace":
                continue
            if len(self.properties) >= MAX_PROPERTIES:
                self.clipped = True
                return
            prop = shared(described)
            topic = topic_of(service, prop.name)
            self.properties[topic] = shared_property(service, prop.name, prop)
            if prop.access in (Access.ACTION, Access.QUERY):
                offered = shared_service(topic, service, prop.name, prop)
                self.services[offered.id] = offered
                continue
            if not prop.access.listenable or prop.needs_parameters:
                continue
            if readable is not None and prop.name not in readable:
                continue
            self._channel(
                topic,
                Kind.VALUE,
                service,
                prop.name,
                prop,
                schemas.value_schema_name(prop),
                value_schema_text(prop, service),
            )
            if schemas.is_pose(prop) and prop.name == schemas.LOCATION:
                self._channel(
                    topic_of(service, "pose"),
                    Kind.POSE,
                    service,
                    prop.name,
                    prop,
                    schemas.POSE_SCHEMA_NAME,
                    POSE_SCHEMA_TEXT,
                )

    def remove(self, service: str) -> tuple[list[int], list[int]]:
        """Forget ``service`` (it left, or is shown again): the ids of its channels and services."""
        channels = [c.id for c in self.channels.values() if c.service == service and c.kind is not Kind.SCENE]
        for channel_id in channels:
            del self.channels[channel_id]
        services = [s.id for s in self.services.values() if s.service == service]
        for service_id in services:
            del self.services[service_id]
        for topic in [t for t, (name, _, _) in self.properties.items() if name == service]:
            del self.properties[topic]
        if len(self.channels) < MAX_CHANNELS:
            self.clipped = False
        return channels, services

    def add_scene(self) -> None:
        """The one channel of every location, once any service has one."""
        if any(c.kind is Kind.SCENE for c in self.channels.values()):
            return
        if any(c.kind is Kind.POSE for c in self.channels.values()):
            self._channel(
                SCENE_TOPIC,
                Kind.SCENE,
                "*",
                schemas.LOCATION,
                None,
                schemas.SCENE_SCHEMA_NAME,
                SCENE_SCHEMA_TEXT,
            )

    def parameter(self, name: str) -> tuple[str, str, PropertyModel] | None:
        """The property a parameter name stands for: a read-write scalar."""
        found = self.properties.get(name)
        if found is None or not is_parameter(found[2]):
            return None
        return found

    def parameter_channel(self, name: str) -> Channel | None:
        """What a subscription to parameter ``name``'s updates follows (no channel is advertised)."""
        found = self.parameter(name)
        if found is None:
            return None
        service, path, prop = found
        return shared_channel((name, Kind.PARAMETER, service, path, prop, "", ""))

    def parameter_names(self) -> list[str]:
        return [topic for topic, (_, _, prop) in self.properties.items() if is_parameter(prop)]


def is_parameter(prop: PropertyModel) -> bool:
    return prop.access is Access.READ_WRITE and prop.type in PARAMETER_TYPES
