"""A service the gateway has not reached yet reads as such in the registry: type unknown, state connecting."""

from __future__ import annotations

import json

from support.gateway_process import StartGateway
from support.ports import free_port
from support.psctl import psctl


def services_table(target: str) -> dict[str, dict[str, str]]:
    done = psctl(target, "--json", "ls", "-l")
    assert done.returncode == 0, done.stderr
    return {row["name"]: row for row in json.loads(done.stdout)}


def test_federated_and_device_services_never_reached_are_unknown_and_connecting(
    gateway_process: StartGateway,
) -> None:
    nobody = free_port()
    gw = gateway_process(f"""
        [[services]]
        name = "faraway"
        url = "grpc://127.0.0.1:{nobody}/scout1"

        [[services]]
        name = "arm"
        url = "tcp://127.0.0.1:{nobody}"

        [[services]]
        name = "scout1"
        type = "sim-robot"
    """)
    rows = services_table(gw.address)
    for name in ("faraway", "arm"):
        assert (rows[name]["type"], rows[name]["state"]) == ("unknown", "connecting"), rows[name]
    assert (rows["scout1"]["type"], rows["scout1"]["state"]) == ("mobile_robot", "up")


def test_the_demo_devices_are_up_with_their_type_once_reached(demo_gateway: object) -> None:
    rows = services_table(demo_gateway.address)  # type: ignore[attr-defined]
    for name in ("rover1", "rover2"):
        assert (rows[name]["type"], rows[name]["state"]) == ("mobile_robot", "up"), rows[name]
