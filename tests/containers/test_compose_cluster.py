"""The compose cluster as a user runs it: etcd, three gateways and three devices, in podman.

Each service of ``compose.cluster.yaml`` is started as the file says (its image, command,
entrypoint, mounted files, and its name on one network), through podman's Docker-compatible API,
the gateways' ports mapped to free host ports: the image this tree built (``image``) stands for
``localhost/psgateway:latest`` and the one setup.sh made or was given (``etcd_image``) for etcd.
The ``register`` container registers each device on one gateway; every gateway answers for every
device; the container of the gateway that owns ``thermo1`` is killed, and within its lease another
gateway owns ``thermo1`` and answers for it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from support.podman_runs import run_labels

from clients import Client
from clients.errors import PropertyServiceError

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
COMPOSE_CLUSTER = ROOT / "compose.cluster.yaml"
GATEWAYS = ("gw1", "gw2", "gw3")
DEVICES = {"thermo1": "gw1", "rover1": "gw2", "thermo2": "gw3"}
GRPC_PORT = 50051
#: Seconds a container may take to serve, and the register container to finish (two cores).
READY = 90.0
#: Seconds for a killed gateway's devices to be owned again: its lease (5 s) and a generous margin.
TAKEN_OVER = 45.0


def _answer(probe: Callable[[], Any]) -> Any:
    try:
        return probe()
    except PropertyServiceError as exc:
        return exc


def wait_for(what: str, probe: Callable[[], Any], good: Callable[[Any], bool], within: float) -> Any:
    """``probe()`` until ``good`` holds for its answer (an error is an answer); fail after ``within`` s."""
    deadline = time.monotonic() + within
    seen = _answer(probe)
    while not good(seen):
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {within} s; last answer {seen!r}")
        time.sleep(0.5)
        seen = _answer(probe)
    return seen


def _start(name: str, spec: dict[str, Any], image: str, network: Any) -> Any:
    """The compose file's service ``name`` as a container on ``network``, reached there by its name."""
    from testcontainers.core.container import DockerContainer

    container = DockerContainer(image).with_network(network).with_network_aliases(name)
    kwargs: dict[str, Any] = {"labels": run_labels()}
    if "entrypoint" in spec:
        kwargs["entrypoint"] = spec["entrypoint"]
    container = container.with_kwargs(**kwargs)
    if "command" in spec:
        container = container.with_command(spec["command"])
    for volume in spec.get("volumes", []):
        source, target, mode = volume.split(":")
        container = container.with_volume_mapping(str(ROOT / source), target, mode)
    for port in spec.get("ports", []):
        container = container.with_exposed_ports(int(port.rpartition(":")[2]))
    container.start()
    return container


@pytest.fixture
def cluster(image: str, etcd_image: str, docker_api: str) -> Iterator[dict[str, Any]]:
    from testcontainers.core.network import Network

    services = yaml.safe_load(COMPOSE_CLUSTER.read_text())["services"]
    with Network(docker_network_kw={"labels": run_labels()}) as network:
        started: dict[str, Any] = {}
        try:
            for name in ("etcd", *DEVICES, *GATEWAYS):
                started[name] = _start(name, services[name], etcd_image if name == "etcd" else image, network)
            yield {"started": started, "services": services, "network": network, "image": image}
        finally:
            for container in started.values():
                container.stop()


def _client(container: Any) -> Client:
    address = f"{container.get_container_host_ip()}:{container.get_exposed_port(GRPC_PORT)}"
    return Client(address, timeout=5.0)


def test_a_device_owned_by_a_killed_gateways_container_is_answered_by_another(
    cluster: dict[str, Any],
) -> None:
    started = cluster["started"]
    clients = {gw: _client(started[gw]) for gw in GATEWAYS}
    try:
        for gw, client in clients.items():
            wait_for(
                f"{gw} serves",
                lambda c=client: c.get("registry", "store"),
                lambda v: v == "etcd://etcd:2379",
                READY,
            )
        register = _start("register", cluster["services"]["register"], cluster["image"], cluster["network"])
        try:
            ended = register.get_wrapped_container().wait(timeout=READY)
            logs = register.get_wrapped_container().logs().decode(errors="replace")
            assert ended["StatusCode"] == 0, logs
        finally:
            register.stop()

        # Every gateway answers for every device, each owned where it was registered.
        for gw, client in clients.items():
            for device, owner in DEVICES.items():
                wait_for(
                    f"{device} owned by {owner}, as {gw} says",
                    lambda c=client, d=device: c.get("registry", f"services.{d}.owner"),
                    lambda seen, o=owner: seen == o,
                    READY,
                )
                assert client.get_names(device, "properties"), f"{device} through {gw}"
        assert clients["gw3"].get("rover1", "location") == "(3 0 0 0 0 0)"

        # The container of thermo1's owner is killed: another gateway owns it and answers for it.
        started["gw1"].get_wrapped_container().kill()
        new_owner = wait_for(
            "thermo1 owned by a survivor",
            lambda: clients["gw2"].get("registry", "services.thermo1.owner"),
            lambda seen: seen in {"gw2", "gw3"},
            TAKEN_OVER,
        )
        for gw in ("gw2", "gw3"):
            wait_for(
                f"thermo1 answered through {gw} (owned by {new_owner})",
                lambda c=clients[gw]: c.get_names("thermo1", "properties"),
                lambda seen: isinstance(seen, list) and len(seen) > 0,
                TAKEN_OVER,
            )
        assert clients["gw3"].get("registry", "services.thermo1.owner") == new_owner
    finally:
        for client in clients.values():
            client.close()
