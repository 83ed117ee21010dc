"""Foxglove's own WebSocket client (npm ``@foxglove/ws-protocol``, in Node with ``ws``) against a
real gateway process.

``tests/interop/foxglove/drive.js`` connects with the subprotocol it is given, lists the channels
and services, subscribes to a robot's pose, its speed and the scene, publishes a speed, reads the
speed parameter and calls ``behaviors.stop``, and prints what it saw as JSON. The packages are
pinned by ``tests/interop/foxglove/package-lock.json`` and installed by ``npm ci`` once per lock
file; without npm or its registry the tests skip, saying so.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import jwt
import pytest
from support.gateway_process import GatewayProcess, StartGateway
from support.npm import NPM_TIMEOUT, npm_ci, tool

ROOT = Path(__file__).resolve().parents[2]
CLIENT_DIR = ROOT / "tests" / "interop" / "foxglove"
DRIVE = CLIENT_DIR / "drive.js"
DRIVE_TIMEOUT = 40.0
SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")

pytestmark = pytest.mark.timeout(NPM_TIMEOUT + 120)

ROBOT = """
[[services]]
name = "bot"
type = "sim-robot"
"""

SECRET = "a shared secret of the lab, long enough for HS256"
RULES = (
    ROBOT
    + """
[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[rules]]
subject = "*"
service = "bot"
operations = ["read"]
effect = "permit"

[[rules]]
subject = "operator"
service = "bot"
operations = ["write", "invoke"]
effect = "permit"
"""
)


@pytest.fixture(scope="session")
def node() -> str:
    """``node``, with the client's packages installed by ``npm ci`` (once per lock file)."""
    what = "the Foxglove client tests"
    node = tool("node", what)
    npm_ci(CLIENT_DIR, what)
    return node


def drive(node: str, gw: GatewayProcess, subprotocol: str, path: str = "", token: str = "") -> dict[str, Any]:
    """Run the client against ``gw`` and return its report."""
    url = f"ws://{gw.http_address}/{path}"
    args = [node, str(DRIVE), url, subprotocol, "bot", *([token] if token else [])]
    done = subprocess.run(
        args, capture_output=True, text=True, timeout=DRIVE_TIMEOUT, check=False, cwd=CLIENT_DIR
    )
    assert done.returncode == 0, done.stderr
    report: dict[str, Any] = json.loads(done.stdout)
    assert not report.get("timedOut"), report
    return report


def token(subject: str) -> str:
    return jwt.encode(
        {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}, SECRET, algorithm="HS256"
    )


@pytest.mark.parametrize("subprotocol", SUBPROTOCOLS)
def test_foxglove_client_subscribes_publishes_and_calls_with_either_subprotocol(
    node: str, gateway_process: StartGateway, subprotocol: str
) -> None:
    gw = gateway_process(ROBOT)
    report = drive(node, gw, subprotocol, path="foxglove")

    assert report["protocol"] == subprotocol
    assert set(report["serverInfo"]["capabilities"]) >= {"clientPublish", "services", "parameters"}
    channels = {c["topic"]: c for c in report["channels"]}
    assert channels["/bot/speed"]["schemaName"] == "propertyservice.Number"
    assert channels["/bot/speed"]["schema"]["properties"]["value"]["type"] == "number"
    assert {c["encoding"] for c in report["channels"]} == {"json"}
    assert {c["schemaEncoding"] for c in report["channels"]} == {"jsonschema"}
    assert channels["/bot/pose"]["schemaName"] == "foxglove.PoseInFrame"
    assert channels["/scene"]["schemaName"] == "foxglove.SceneUpdate"

    pose = report["messages"]["/bot/pose"][0]["body"]
    assert pose["frame_id"] == "world"
    assert pose["pose"]["position"] == {"x": 0, "y": 0, "z": 0}
    assert pose["pose"]["orientation"]["w"] == 1
    scene = report["messages"]["/scene"][0]["body"]
    assert [entity["id"] for entity in scene["entities"]] == ["bot"]
    # The current speed first, then the one the client published: the publish was a Set.
    assert [m["body"]["value"] for m in report["messages"]["/bot/speed"]] == [0.5, 0.7]
    assert report["parameters"]["parameters"] == [{"name": "/bot/speed", "value": 0.7}]
    assert report["parameters"]["id"] == "after-publish"

    services = {s["name"]: s for s in report["services"]}
    assert services["/bot/behaviors/moveto"]["type"] == "propertyservice/Action"
    assert services["/registry/find"]["type"] == "propertyservice/Query"
    stop = services["/bot/behaviors/stop"]["id"]
    assert report["serviceResponses"] == [
        {"serviceId": stop, "callId": 41, "encoding": "json", "body": {"value": ""}}
    ]
    assert report["statuses"] == []
    gw.stop()


def test_foxglove_client_dialling_the_root_path_is_served(node: str, gateway_process: StartGateway) -> None:
    gw = gateway_process(ROBOT)
    report = drive(node, gw, "foxglove.websocket.v1")
    assert report["protocol"] == "foxglove.websocket.v1"
    assert [m["body"]["value"] for m in report["messages"]["/bot/speed"]] == [0.5, 0.7]


def test_rules_refuse_an_anonymous_publish_and_service_call_and_let_the_operator(
    node: str, gateway_process: StartGateway, tmp_path: Path
) -> None:
    (tmp_path / "jwt.secret").write_text(SECRET)
    gw = gateway_process(RULES)

    anonymous = drive(node, gw, "foxglove.websocket.v1", path="foxglove")
    # It reads (the rules permit everyone), but neither its publish nor its call passes.
    assert [m["body"]["value"] for m in anonymous["messages"]["/bot/speed"]] == [0.5]
    errors = [s["message"] for s in anonymous["statuses"] if s["level"] == 2]
    assert any(m.startswith("publish /bot/speed: UNAUTHENTICATED") for m in errors), errors
    assert anonymous["serviceResponses"] == []
    assert [f["callId"] for f in anonymous["serviceFailures"]] == [41]
    assert "UNAUTHENTICATED" in anonymous["serviceFailures"][0]["message"]
    assert anonymous["parameters"]["parameters"] == [{"name": "/bot/speed", "value": 0.5}]

    operator = drive(node, gw, "foxglove.websocket.v1", path="foxglove", token=token("operator"))
    assert [m["body"]["value"] for m in operator["messages"]["/bot/speed"]] == [0.5, 0.7]
    assert operator["statuses"] == []
    assert [r["callId"] for r in operator["serviceResponses"]] == [41]

    guest = drive(node, gw, "foxglove.websocket.v1", path="foxglove", token=token("guest"))
    errors = [s["message"] for s in guest["statuses"] if s["level"] == 2]
    assert any(m.startswith("publish /bot/speed: PERMISSION_DENIED") for m in errors), errors
    gw.stop()
