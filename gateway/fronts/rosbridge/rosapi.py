"""rosapi's introspection services, answered from the registry and the services' models.

Generic ROS web tools (and roslibjs's ``getTopics``, ``getServices``, ``getNodes`` …, roslibpy's
``get_topics`` …) ask rosapi what there is. Here every service the registry lists is a node
(``/scout1``); each property a Listen may follow is a topic it publishes, each one a client may
write a topic it subscribes to, with the robot conventions (``cmd_vel``, ``odom``, ``pose``) for
mobile robots; each action and query is a service. What the caller may not read is not listed.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.config import REGISTRY_NAME
from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.rules import Operation, Subject
from gateway.engine.types import DescribeCall, GetCall
from services.kernel import ros_messages as messages
from services.kernel.errors import InvalidArgument, NotFound, PropertyError
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.ros_names import CONVENTIONS, MOBILE_ROBOT, ros_name
from services.kernel.values import parse_names

ROSAPI_PREFIX = "/rosapi/"
#: Services listed at most (rosapi answers in one message): a registry of more lists its first ones.
MAX_LISTED_SERVICES = 1000
#: Describe calls running at once while a listing is made.
DESCRIBES_AT_ONCE = 8
#: Service types: an action that takes no value answers as std_srvs/Trigger does.
TRIGGER = "std_srvs/Trigger"
ACTION = "propertyservice/Action"
QUERY = "propertyservice/Query"
#: rosapi's own services and their types, as rosapi names them.
ROSAPI_SERVICES = {
    "/rosapi/topics": "rosapi/Topics",
    "/rosapi/topics_for_type": "rosapi/TopicsForType",
    "/rosapi/topic_type": "rosapi/TopicType",
    "/rosapi/services": "rosapi/Services",
    "/rosapi/services_for_type": "rosapi/ServicesForType",
    "/rosapi/service_type": "rosapi/ServiceType",
    "/rosapi/nodes": "rosapi/Nodes",
    "/rosapi/node_details": "rosapi/NodeDetails",
    "/rosapi/get_time": "rosapi/GetTime",
}


@dataclass
class Graph:
    """What the caller may see: topics with their types, services with theirs, nodes."""

    topics: dict[str, str] = field(default_factory=dict)
    services: dict[str, str] = field(default_factory=dict)
    #: node → (topics it publishes, topics it subscribes to, its services)
    nodes: dict[str, tuple[list[str], list[str], list[str]]] = field(default_factory=dict)


def service_type(prop: PropertyModel) -> str:
    if prop.access == Access.QUERY:
        return QUERY
    return TRIGGER if prop.value is None else ACTION


def add_service(graph: Graph, name: str, model: ServiceModel, may: Any) -> None:
    """``name``'s topics and services into ``graph`` (``may(path, operation)``: the rules' say)."""
    published: list[str] = []
    subscribed: list[str] = []
    services: list[str] = []
    for prop in model.properties:
        if prop.type == "namespace":
            continue
        topic = ros_name(name, prop.name)
        if prop.access in (Access.ACTION, Access.QUERY):
            operation = Operation.INVOKE if prop.access == Access.ACTION else Operation.READ
            if may(prop.name, operation):
                graph.services[topic] = service_type(prop)
                services.append(topic)
            continue
        listed = False
        if prop.access.listenable and not prop.needs_parameters and may(prop.name, Operation.READ):
            published.append(topic)
            listed = True
        if prop.access.writable and may(prop.name, Operation.WRITE):
            subscribed.append(topic)
            listed = True
        if listed:
            graph.topics[topic] = messages.default_type(prop)
    if model.type == MOBILE_ROBOT:
        by_name = {p.name: p for p in model.properties}
        for convention, (path, type_name) in CONVENTIONS.items():
            underlying = by_name.get(path)
            if underlying is None:
                continue
            topic = f"/{name}/{convention}"
            if convention == "cmd_vel" and underlying.access.writable and may(path, Operation.WRITE):
                subscribed.append(topic)
                graph.topics[topic] = type_name
            elif convention != "cmd_vel" and may(path, Operation.READ):
                published.append(topic)
                graph.topics[topic] = type_name
    graph.nodes[f"/{name}"] = (published, subscribed, services)


class Rosapi:
    """The answers of ``/rosapi/...`` service calls for one caller at a time."""

    def __init__(self, calls: Calls, guard: Guard) -> None:
        self.calls = calls
        self.guard = guard

    async def graph(self, subject: Subject) -> Graph:
        """Every service's topics and services that ``subject`` may see, read now."""
        timeout = self.calls.timeout
        listing = await self.calls.get(GetCall(REGISTRY_NAME, "services"), timeout, subject)
        value = listing.value if isinstance(listing.value, str) else ""
        names = parse_names(value)[:MAX_LISTED_SERVICES]
        places = asyncio.Semaphore(DESCRIBES_AT_ONCE)

        async def describe(name: str) -> ServiceModel | None:
            async with places:
                try:
                    return await self.calls.describe(DescribeCall(name), timeout, subject)
                except PropertyError:
                    return None  # refused, gone or unreachable: not listed

        models = await asyncio.gather(*(describe(name) for name in names))
        graph = Graph(services=dict(ROSAPI_SERVICES))
        for name, model in zip(names, models, strict=True):
            if model is None:
                continue

            def may(path: str, operation: Operation, service: str = name) -> bool:
                return self.guard.may(subject, service, path, operation)

            add_service(graph, name, model, may)
        return graph

    async def answer(self, service: str, args: Any, subject: Subject) -> dict[str, Any]:
        """The response values of rosapi service ``service``; NotFound for one not answered here."""
        if args is None or (isinstance(args, list) and not args):
            args = {}
        if not isinstance(args, Mapping):
            raise InvalidArgument(f"{service[:200]}: args must be a JSON object")
        if service == "/rosapi/get_time":
            seconds, nanoseconds = divmod(time.time_ns(), 1_000_000_000)
            return {"time": {"secs": seconds, "nsecs": nanoseconds, "sec": seconds, "nanosec": nanoseconds}}
        if service not in ROSAPI_SERVICES:
            raise NotFound(
                f"{service[:200]} is not answered here (answered: {', '.join(sorted(ROSAPI_SERVICES))})"
            )
        graph = await self.graph(subject)
        if service == "/rosapi/topics":
            topics = sorted(graph.topics)
            return {"topics": topics, "types": [graph.topics[t] for t in topics]}
        if service == "/rosapi/topics_for_type":
            wanted = messages.canonical(_arg(args, "type", service))
            return {"topics": sorted(t for t, kind in graph.topics.items() if kind == wanted)}
        if service == "/rosapi/topic_type":
            return {"type": graph.topics.get(_arg(args, "topic", service), "")}
        if service == "/rosapi/services":
            return {"services": sorted(graph.services)}
        if service == "/rosapi/services_for_type":
            wanted = _arg(args, "type", service)
            return {"services": sorted(s for s, kind in graph.services.items() if kind == wanted)}
        if service == "/rosapi/service_type":
            return {"type": graph.services.get(_arg(args, "service", service), "")}
        if service == "/rosapi/nodes":
            return {"nodes": sorted(graph.nodes)}
        # /rosapi/node_details
        node = _arg(args, "node", service)
        publishing, subscribing, services = graph.nodes.get(node, ([], [], []))
        return {"publishing": publishing, "subscribing": subscribing, "services": services}


def _arg(args: Mapping[str, Any], key: str, service: str) -> str:
    value = args.get(key)
    if not isinstance(value, str):
        raise InvalidArgument(f"{service[:200]} takes {key!r}, a string")
    return value
