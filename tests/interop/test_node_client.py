"""The Node.js example client (clients/examples/node) against a real gateway process.

The client loads the same .proto at run time with @grpc/proto-loader and calls the gateway
through @grpc/grpc-js: a second language, a second gRPC stack, one contract.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import re
import subprocess
from pathlib import Path
from typing import Any

import grpc
import pytest
from support.certs import make_certificates
from support.npm import NPM_TIMEOUT, npm_ci, tool

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

ROOT = Path(__file__).resolve().parents[2]
NODE_DIR = ROOT / "clients" / "examples" / "node"
PROPCTL = NODE_DIR / "propctl.mjs"
NODE_MAJOR = 18
CALL_TIMEOUT = 30.0
MOVETO = "<marker><location>(2.0 1.0 0 0 0 0)</location></marker>"
TARGET_XY = (2.0, 1.0)
INSTALL_HINT = (
    f"the Node.js client tests need node >= {NODE_MAJOR} and npm on PATH: "
    "tests/run.sh installs them with apt-get when missing (Debian packages nodejs and npm)"
)

# The first test of the session also carries the one-time `npm ci` (bounded by NPM_TIMEOUT).
pytestmark = pytest.mark.timeout(NPM_TIMEOUT + 60)


@pytest.fixture(scope="session")
def node() -> str:
    """The `node` binary, with the client's packages installed by `npm ci` (once per lock file)."""
    node = tool("node", INSTALL_HINT, required=True)
    version = subprocess.run(
        [node, "--version"], check=False, capture_output=True, text=True, timeout=30
    ).stdout
    m = re.match(r"v(\d+)\.", version)
    if m is None or int(m.group(1)) < NODE_MAJOR:
        pytest.fail(f"node {version.strip()} is too old; {INSTALL_HINT}", pytrace=False)
    npm_ci(NODE_DIR, "the Node.js client tests", required=True)
    return node


def propctl(node: str, gw: Any, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [node, str(PROPCTL), "-t", gw.address, *args],
        cwd=NODE_DIR,
        check=False,
        capture_output=True,
        text=True,
        timeout=CALL_TIMEOUT,
    )


def json_lines(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def python_get(gw: Any, service: str, prop: str) -> str:
    with grpc.insecure_channel(gw.address) as channel:
        reply = pb_grpc.PropertyServiceStub(channel).Get(
            pb.GetRequest(service=service, property=prop), timeout=CALL_TIMEOUT
        )
    return str(reply.value)


def xy(vector: str) -> tuple[float, float]:
    x, y, *_ = (float(v) for v in vector.strip("()").split())
    return x, y


def test_get_reads_what_the_python_stub_reads(node: str, demo_gateway: Any) -> None:
    done = propctl(node, demo_gateway, "get", "scout1", "properties")
    assert done.returncode == 0, done.stderr
    [line] = json_lines(done.stdout)
    assert line["service"] == "scout1" and line["property"] == "properties"
    assert line["value"] == python_get(demo_gateway, "scout1", "properties")
    assert "behaviors.moveto" in line["value"].strip("()").split()

    done = propctl(node, demo_gateway, "get", "scout1", "location.x")
    assert done.returncode == 0, done.stderr
    [line] = json_lines(done.stdout)
    assert math.isfinite(float(line["value"]))


async def spawn(node: str, gw: Any, *args: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        node,
        str(PROPCTL),
        "-t",
        gw.address,
        *args,
        cwd=NODE_DIR,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )


async def test_listen_sees_the_robot_drive_to_a_target_set_from_node(node: str, demo_gateway: Any) -> None:
    before = python_get(demo_gateway, "scout1", "location")  # the robot is idle: nothing moved it yet
    listen = await spawn(node, demo_gateway, "listen", "scout1", "location", "--count", "6", "--marks")
    stdout = listen.stdout
    assert stdout is not None

    async def line() -> dict[str, Any]:
        text = await asyncio.wait_for(stdout.readline(), CALL_TIMEOUT)
        assert text, "the Node listen ended early"
        parsed: dict[str, Any] = json.loads(text)
        return parsed

    try:
        first = await line()
        assert (first["service"], first["property"], first["value"]) == ("scout1", "location", before)
        assert first["sequence"] == 1 and first["gap"] is False and first["removed"] is False
        assert await line() == {"sync": True}

        setter = await spawn(node, demo_gateway, "set", "scout1", "behaviors.moveto", MOVETO)
        out, err = await asyncio.wait_for(setter.communicate(), CALL_TIMEOUT)
        assert setter.returncode == 0, err.decode()
        assert json_lines(out.decode())[0]["property"] == "behaviors.moveto"

        moves = [await line() for _ in range(5)]
        assert [e["sequence"] for e in moves] == [2, 3, 4, 5, 6]
        assert await asyncio.wait_for(listen.wait(), CALL_TIMEOUT) == 0  # --count ended it cleanly
        distances = [math.dist(xy(e["value"]), TARGET_XY) for e in [first, *moves]]
        assert all(b <= a + 1e-9 for a, b in itertools.pairwise(distances)), distances
        assert distances[-1] < distances[0]
    finally:
        if listen.returncode is None:
            listen.kill()
            await listen.wait()
        stop = await spawn(node, demo_gateway, "set", "scout1", "behaviors.stop", "")
        await asyncio.wait_for(stop.communicate(), CALL_TIMEOUT)


def test_unknown_service_prints_not_found_and_fails(node: str, demo_gateway: Any) -> None:
    done = propctl(node, demo_gateway, "get", "scoutX", "location")
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr.startswith("error: NOT_FOUND: ")
    assert "scoutX" in done.stderr


def test_session_reports_each_tagged_get_on_its_own_reply(node: str, demo_gateway: Any) -> None:
    done = propctl(node, demo_gateway, "session", "scout2:location", "nosuch:location")
    assert done.returncode == 1, done.stderr  # one request failed; the session itself ended cleanly
    assert done.stderr == ""
    replies = {line["id"]: line for line in json_lines(done.stdout)}
    assert set(replies) == {1, 2}
    assert replies[1] == {"id": 1, "code": "OK", "value": python_get(demo_gateway, "scout2", "location")}
    assert replies[2]["code"] == "NOT_FOUND"
    assert "nosuch" in replies[2]["message"]


def test_get_over_mutual_tls_with_a_token(node: str, gateway_process: Any, tmp_path: Path) -> None:
    certs = make_certificates(tmp_path / "certs")
    alice = certs.clients["alice"]
    gw = gateway_process(
        f"""
        [tls]
        cert = "{certs.server.cert}"
        key = "{certs.server.key}"
        client_ca = "{certs.ca}"
        require_client_cert = true
        [[services]]
        name = "bot"
        type = "sim-robot"
        """,
        credentials=grpc.ssl_channel_credentials(
            certs.ca.read_bytes(), alice.key.read_bytes(), alice.cert.read_bytes()
        ),
    )
    tls = ["--ca", str(certs.ca), "--cert", str(alice.cert), "--key", str(alice.key), "--token", "t0k"]
    done = propctl(node, gw, *tls, "get", "bot", "location")
    assert done.returncode == 0, done.stderr
    assert json_lines(done.stdout)[0]["value"].startswith("(")
    refused = propctl(node, gw, "--ca", str(certs.ca), "get", "bot", "location")
    assert refused.returncode == 3, refused.stderr
