"""Part (u): rosbridge v2 subscribers beside gRPC Listen and SSE, and a ``cmd_vel`` round trip.

Fan-out: one gateway process serves the bench service on its gRPC port and its HTTP front end; the
same setter as part (k) (one gRPC client, one unary Set at a time, the value being
``str(time.perf_counter_ns())``) drives, in turn on that gateway:

* ``grpc``: ``subscribers`` gRPC Listen streams on ``bench/value`` (part (c)'s one-by-one run);
* ``sse``: ``subscribers`` event streams on it (part (k));
* ``rosbridge``: ``subscribers`` WebSocket connections to ``/rosbridge``, each sending rosbridge's
  ``subscribe`` of the topic ``/bench/value`` (``std_msgs/String``) and reading its ``publish``
  messages, as that many roslibjs pages would (from several loopback addresses, 50 each).

The ways take turns over the rounds, each round on a fresh gateway, and each reports its best
round; the ratios are rosbridge's figures over gRPC's and over SSE's of the same run.

Round trip: on a gateway that also serves a simulated robot, one rosbridge connection subscribes
to ``/robot/velocity`` and publishes ``geometry_msgs/Twist`` on ``/robot/cmd_vel``, as a roslibjs
joystick does; each Twist asks a speed the previous one did not, and the time from its publish
to the first velocity message showing that speed is one sample.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import aiohttp
import grpc

from bench.listen import (
    CALL_TIMEOUT,
    CHANNEL_OPTIONS,
    ListenResult,
    Run,
    count_delivery,
    measure_delivery,
    run_listen,
)
from bench.measure import Latencies
from bench.servers import ServerProcess
from bench.sse import ARGV, http_url, run_sse_listen, sessions_from_sources
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

TOPIC = f"/{SERVICE}/{VALUE_PROPERTY}"
ROBOT = "robot"
#: The round trip's gateway: the bench service and one simulated robot served in-process.
ROBOT_CONFIG = f"""
[[services]]
name = "{ROBOT}"
type = "sim-robot"
"""
#: Seconds a subscriber waits to see its subscription live (a first message) before giving up.
SUBSCRIBE_TIMEOUT = 10.0
#: Speeds the round trip asks in turn (m/s): each differs from the one before, all below the
#: simulated robot's max_speed, so the velocity read back equals the Twist sent.
ROUND_TRIP_SPEEDS = tuple(round(0.1 + 0.002 * n, 3) for n in range(50))
#: How close (m/s) a velocity read back must be to the speed asked: a quarter of the steps between
#: speeds, room for a value that went through text.
SPEED_MATCH = 5e-4


class _RosbridgeSubscriber:
    """One WebSocket connection with one rosbridge subscription, and what it has read."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse, run: Run) -> None:
        self.ws = ws
        self.run = run
        self.latest = ""
        self.events = 0
        self.last_ns = 0
        self.seen = asyncio.Event()
        self.done = asyncio.Event()
        self.measuring = False

    async def subscribe(self, number: int) -> None:
        await self.ws.send_json(
            {"op": "subscribe", "id": f"sub{number}", "topic": TOPIC, "type": "std_msgs/String"}
        )

    def check_done(self) -> None:
        final = self.run.final
        if self.events >= self.run.expected or (final is not None and self.latest == final[VALUE_PROPERTY]):
            self.done.set()

    async def consume(self) -> None:
        samples = self.run.samples
        async for message in self.ws:
            if message.type != aiohttp.WSMsgType.TEXT:
                break
            now = time.perf_counter_ns()
            data = json.loads(message.data)
            if data.get("op") != "publish" or data.get("topic") != TOPIC:
                continue
            self.seen.set()
            if not self.measuring:
                continue
            value = data["msg"]["data"]
            self.events += 1
            self.latest = value
            samples.append(now - int(value))
            self.last_ns = now
            self.check_done()


async def run_rosbridge_listen(
    server: ServerProcess, base_url: str, *, subscribers: int, sets: int, set_rate: float, time_limit: float
) -> ListenResult:
    """``subscribers`` rosbridge subscriptions of ``/bench/value``, ``sets`` gRPC Sets, arrivals counted."""
    result = ListenResult(
        mode="rosbridge",
        subscribers=subscribers,
        sets=sets,
        properties=1,
        burst=1,
        set_rate=set_rate,
        channels=subscribers,
    )
    run = Run(expected=sets)
    deadline = time.monotonic() + time_limit
    url = f"{base_url}rosbridge"
    subs: list[_RosbridgeSubscriber] = []
    tasks: list[asyncio.Task[None]] = []
    first_set_ns = 0
    async with (
        contextlib.AsyncExitStack() as stack,
        grpc.aio.insecure_channel(server.address, options=CHANNEL_OPTIONS) as setter_channel,
    ):
        sessions = await sessions_from_sources(stack, subscribers)
        try:
            setter = pb_grpc.PropertyServiceStub(setter_channel)
            async with asyncio.timeout(CALL_TIMEOUT * 3):
                sockets = await asyncio.gather(
                    *(sessions[n % len(sessions)].ws_connect(url, max_msg_size=0) for n in range(subscribers))
                )
                subs = [_RosbridgeSubscriber(ws, run) for ws in sockets]
                tasks = [asyncio.create_task(sub.consume()) for sub in subs]
                await asyncio.gather(*(sub.subscribe(n) for n, sub in enumerate(subs)))
            # rosbridge promises no current value on subscribe: Sets (not measured) until every
            # subscription has shown it is live.
            async with asyncio.timeout(SUBSCRIBE_TIMEOUT):
                while not all(sub.seen.is_set() for sub in subs):
                    await setter.Set(
                        pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value="0"),
                        timeout=CALL_TIMEOUT,
                    )
                    await asyncio.sleep(0.05)
            await asyncio.sleep(0.2)  # the warm-up Sets' messages are read before counting starts
            for sub in subs:
                sub.measuring = True
            first_set_ns = await measure_delivery(
                server,
                setter,
                subs,
                run,
                result,
                properties=(VALUE_PROPERTY,),
                sets=sets,
                set_rate=set_rate,
                deadline=deadline,
            )
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await asyncio.gather(*(sub.ws.close() for sub in subs), return_exceptions=True)
    count_delivery(result, subs, run, first_set_ns)
    # rosbridge has no count of values left out: every Set a subscriber missed was conflated.
    result.conflated = sets * subscribers - result.events if all(s.done.is_set() for s in subs) else 0
    result.messages = result.events
    result.complete_subscribers = sum(sub.done.is_set() for sub in subs)
    server.check_alive()
    return result


async def cmd_vel_round_trip(trips: int, time_limit: float) -> dict[str, Any]:
    """``trips`` Twists published on ``/robot/cmd_vel``, each timed until ``/robot/velocity`` shows it."""
    with tempfile.TemporaryDirectory(prefix="bench-rosbridge-") as folder:
        config = Path(folder) / "robot.toml"
        config.write_text(ROBOT_CONFIG)
        server = await ServerProcess.start("gateway with a robot", [*ARGV, "--config", str(config)])
        try:
            samples: list[int] = []
            async with (
                aiohttp.ClientSession() as session,
                session.ws_connect(f"{http_url(server)}rosbridge") as ws,
                asyncio.timeout(time_limit),
            ):
                await ws.send_json(
                    {
                        "op": "subscribe",
                        "topic": f"/{ROBOT}/velocity",
                        "type": "std_msgs/Float64MultiArray",
                    }
                )
                await ws.send_json(
                    {"op": "advertise", "topic": f"/{ROBOT}/cmd_vel", "type": "geometry_msgs/Twist"}
                )
                for n in range(trips):
                    speed = ROUND_TRIP_SPEEDS[n % len(ROUND_TRIP_SPEEDS)]
                    sent = time.perf_counter_ns()
                    await ws.send_json({"op": "publish", "topic": f"/{ROBOT}/cmd_vel", "msg": _twist(speed)})
                    async for message in ws:
                        if message.type != aiohttp.WSMsgType.TEXT:
                            raise RuntimeError(f"the rosbridge connection ended: {message.type.name}")
                        data = json.loads(message.data)
                        if data.get("op") == "publish" and abs(_speed(data["msg"]) - speed) < SPEED_MATCH:
                            samples.append(time.perf_counter_ns() - sent)
                            break
                await ws.send_json({"op": "publish", "topic": f"/{ROBOT}/cmd_vel", "msg": _twist(0.0)})
            server.check_alive()
        finally:
            await server.stop()
    return {"trips": trips, "done": len(samples), "latency": Latencies.of(samples).as_dict()}


def _twist(speed: float) -> dict[str, Any]:
    return {"linear": {"x": speed, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}


def _speed(message: dict[str, Any]) -> float:
    """The planar speed of a ``std_msgs/Float64MultiArray`` velocity (vx vy vz wx wy wz)."""
    data = message.get("data") or [0.0, 0.0]
    return math.hypot(float(data[0]), float(data[1]))


async def run_rosbridge(
    *, subscribers: int, sets: int, set_rate: float, rounds: int, time_limit: float, trips: int
) -> dict[str, Any]:
    """gRPC Listen, SSE and rosbridge fan-out on the same gateway, taking turns (the best round of
    each), then ``trips`` cmd_vel round trips on a fresh gateway with a robot."""
    best: dict[str, Any] = {}
    ways = ["grpc", "sse", "rosbridge"]
    for number in range(rounds):
        server = await ServerProcess.start("gateway with HTTP", ARGV)
        try:
            base_url = http_url(server)
            turn = ways[number % 3 :] + ways[: number % 3]
            for way in turn:
                if way == "grpc":
                    measured = await run_listen(
                        server,
                        mode="one-by-one",
                        properties=(VALUE_PROPERTY,),
                        subscribers=subscribers,
                        sets=sets,
                        channels=math.ceil(subscribers / 25),
                        set_rate=set_rate,
                        time_limit=time_limit,
                    )
                else:
                    run_way = run_sse_listen if way == "sse" else run_rosbridge_listen
                    measured = await run_way(
                        server,
                        base_url,
                        subscribers=subscribers,
                        sets=sets,
                        set_rate=set_rate,
                        time_limit=time_limit,
                    )
                data = measured.as_dict()
                if way not in best or data["events_per_s"] > best[way]["events_per_s"]:
                    best[way] = data
        finally:
            await server.stop()
    best["cmd_vel"] = await cmd_vel_round_trip(trips, time_limit)
    return best
