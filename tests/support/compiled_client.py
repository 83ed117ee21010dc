"""The compiled example clients (clients/examples/cpp, clients/examples/go) from Python tests.

Each is a ``propctl`` binary with the same commands and output as the Node.js client: ``get``,
``set``, ``listen`` (current values, then the sync marker, then it ends) and ``session``, one JSON
line per result on stdout, ``error: CODE: message`` on stderr. ``require_tools`` skips a test on a
machine without the toolchain; ``build_step`` runs one build command (its output is the failure
message); :class:`CompiledClient` runs the binary against a gateway; the ``check_*`` functions
are the test bodies both languages share, so that they cannot drift apart. The build folders live under
``build/`` at the repository root and are kept between runs, so that a second run only relinks.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import pytest

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

ROOT = Path(__file__).resolve().parents[2]
BUILD = ROOT / "build"
# A cold build on two busy cores: C++ ~1 min, Go ~15 s (the grpc-go packages compile once, then
# come from the cache).
BUILD_TIMEOUT = 600.0
CALL_TIMEOUT = 30.0
GO_SOURCES = Path("/usr/share/gocode/src")
GO_HINT = (
    "tests/run.sh installs it with apt-get when missing (Debian packages golang-go, "
    "golang-google-grpc-dev, golang-google-protobuf-dev, golang-github-golang-protobuf-1-5-dev, "
    "protobuf-compiler, protoc-gen-go, protoc-gen-go-grpc)"
)
CPP_HINT = (
    "tests/run.sh installs it with apt-get when missing "
    "(Debian packages cmake, g++, libgrpc++-dev, protobuf-compiler-grpc)"
)


def require_tools(what: str, tools: dict[str, Path | str], hint: str) -> None:
    """Skip the test, naming what is missing, unless every tool (a command or a path) is there."""
    lacking = [
        name
        for name, tool in tools.items()
        if not (Path(tool).exists() if isinstance(tool, Path) else shutil.which(tool))
    ]
    if lacking:
        pytest.skip(f"{what} needs {', '.join(lacking)}: {hint}")


def build_step(args: Sequence[str | Path], cwd: Path = ROOT) -> None:
    """Run one build command; a failure fails the test with the command's output."""
    try:
        done = subprocess.run(
            [str(a) for a in args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=BUILD_TIMEOUT,
            check=False,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"`{' '.join(map(str, args))}` took longer than {BUILD_TIMEOUT:.0f} s", pytrace=False)
    if done.returncode != 0:
        pytest.fail(f"`{' '.join(map(str, args))}` failed:\n{done.stdout}\n{done.stderr}", pytrace=False)


@dataclass(frozen=True)
class CompiledClient:
    """A built ``propctl`` binary."""

    binary: Path

    def run(self, target: str, *args: str) -> subprocess.CompletedProcess[str]:
        """``propctl -t TARGET ARGS...``; never raises on a non-zero exit (tests check it)."""
        return subprocess.run(
            [str(self.binary), "-t", target, *args],
            capture_output=True,
            text=True,
            timeout=CALL_TIMEOUT,
            check=False,
        )


def build_go_client() -> CompiledClient:
    """clients/examples/go built into build/go (its Go build cache kept there); skips without Go."""
    require_tools(
        "the Go client",
        {
            "go": "go",
            "protoc": "protoc",
            "protoc-gen-go": "protoc-gen-go",
            "protoc-gen-go-grpc": "protoc-gen-go-grpc",
            "grpc-go's sources": GO_SOURCES / "google.golang.org" / "grpc",
            "protobuf-go's sources": GO_SOURCES / "google.golang.org" / "protobuf",
            "golang/protobuf 1.5's sources": GO_SOURCES / "github.com/golang/protobuf/proto/registry.go",
        },
        GO_HINT,
    )
    build_step([ROOT / "clients" / "examples" / "go" / "build.sh", BUILD / "go"])
    return CompiledClient(BUILD / "go" / "bin" / "propctl")


def build_cpp_client() -> CompiledClient:
    """clients/examples/cpp built with CMake into build/cpp; skips without the C++ toolchain."""
    require_tools(
        "the C++ client",
        {
            "cmake": "cmake",
            "a C++ compiler": "c++",
            "protoc": "protoc",
            "grpc_cpp_plugin": "grpc_cpp_plugin",
            "gRPC C++'s headers": Path("/usr/include/grpcpp/grpcpp.h"),
        },
        CPP_HINT,
    )
    build = BUILD / "cpp"
    if not (build / "CMakeCache.txt").is_file():
        build_step(["cmake", "-S", ROOT / "clients" / "examples" / "cpp", "-B", build])
    build_step(["cmake", "--build", build, "-j2"])
    return CompiledClient(build / "propctl")


def json_lines(text: str) -> list[dict[str, Any]]:
    """Every line of the client's stdout, parsed."""
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def python_get(gw: Any, service: str, prop: str) -> str:
    with grpc.insecure_channel(gw.address) as channel:
        reply = pb_grpc.PropertyServiceStub(channel).Get(
            pb.GetRequest(service=service, property=prop), timeout=CALL_TIMEOUT
        )
    return str(reply.value)


def check_get_reads_what_the_python_stub_reads(client: CompiledClient, gw: Any) -> None:
    done = client.run(gw.address, "get", "scout1", "properties")
    assert done.returncode == 0, done.stderr
    assert json_lines(done.stdout) == [
        {"service": "scout1", "property": "properties", "value": python_get(gw, "scout1", "properties")}
    ]
    assert "behaviors.moveto" in json_lines(done.stdout)[0]["value"].strip("()").split()


def check_set_is_seen_by_python_and_by_a_listen_until_sync(client: CompiledClient, gw: Any) -> None:
    before = python_get(gw, "scout1", "max_speed")
    try:
        done = client.run(gw.address, "set", "scout1", "max_speed", "0.35")
        assert done.returncode == 0, done.stderr
        [line] = json_lines(done.stdout)
        assert (line["service"], line["property"]) == ("scout1", "max_speed")
        assert float(python_get(gw, "scout1", "max_speed")) == 0.35

        done = client.run(gw.address, "listen", "scout1", "max_speed")
        assert done.returncode == 0, done.stderr
        assert json_lines(done.stdout) == [
            {
                "service": "scout1",
                "property": "max_speed",
                "value": python_get(gw, "scout1", "max_speed"),
                "sequence": 1,
                "conflated": 0,
                "gap": False,
                "removed": False,
            },
            {"sync": True},
        ]
    finally:
        client.run(gw.address, "set", "scout1", "max_speed", before)


def check_listen_with_a_wildcard_prints_every_match_then_sync(client: CompiledClient, gw: Any) -> None:
    done = client.run(gw.address, "listen", "*", "location.x")
    assert done.returncode == 0, done.stderr
    *events, last = json_lines(done.stdout)
    assert last == {"sync": True}
    assert [e["sequence"] for e in events] == list(range(1, len(events) + 1))
    services = {e["service"] for e in events}
    assert {"scout1", "scout2"} <= services
    for e in events:
        assert e["property"] == "location.x"
        float(e["value"])


def check_session_reports_each_tagged_get_on_its_own_reply(client: CompiledClient, gw: Any) -> None:
    done = client.run(gw.address, "session", "scout2:location", "nosuch:location")
    assert done.returncode == 1, done.stderr  # one request failed; the session itself ended cleanly
    assert done.stderr == ""
    replies = {line["id"]: line for line in json_lines(done.stdout)}
    assert set(replies) == {1, 2}
    assert replies[1] == {"id": 1, "code": "OK", "value": python_get(gw, "scout2", "location")}
    assert replies[2]["code"] == "NOT_FOUND"
    assert "nosuch" in replies[2]["message"]


def check_errors_are_one_line_with_the_status_code(client: CompiledClient, gw: Any) -> None:
    done = client.run(gw.address, "get", "scoutX", "location")
    assert (done.returncode, done.stdout) == (1, "")
    assert done.stderr.startswith("error: NOT_FOUND: ") and "scoutX" in done.stderr

    done = client.run(gw.address, "set", "scout1", "max_speed", "fast")
    assert (done.returncode, done.stdout) == (1, "")
    assert done.stderr.startswith("error: INVALID_ARGUMENT: ")

    done = client.run(gw.address, "get", "scout1")
    assert done.returncode == 2 and done.stderr.startswith("error: get takes SERVICE PATH")


def check_an_unreachable_gateway_exits_3(client: CompiledClient, free_port: int) -> None:
    done = client.run(f"127.0.0.1:{free_port}", "get", "scout1", "location")
    assert (done.returncode, done.stdout) == (3, "")
    assert done.stderr.startswith("error: UNAVAILABLE: ")
