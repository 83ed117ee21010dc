"""Gateways whose grpc:// services lead to each other: a request stops at its first turn round the loop."""

from __future__ import annotations

import time

import pytest
from support.ports import free_port

from clients.errors import InvalidArgument, Unavailable
from clients.sync import Client


def test_a_request_that_comes_back_round_a_loop_is_refused_at_once(gateway_process) -> None:  # type: ignore[no-untyped-def]
    port_a, port_b = free_port(), free_port()
    a = gateway_process(
        f'[[services]]\nname = "far"\nurl = "grpc://127.0.0.1:{port_b}/back"\n'
        '[[services]]\nname = "scout1"\ntype = "sim-robot"\n',
        extra_args=("--listen", f"127.0.0.1:{port_a}"),
    )
    b = gateway_process(
        f'[[services]]\nname = "back"\nurl = "grpc://127.0.0.1:{port_a}/far"\n',
        extra_args=("--listen", f"127.0.0.1:{port_b}"),
    )
    with Client(a.address, timeout=8) as client:
        _until_both_are_up(client, "far")
        began = time.monotonic()
        with pytest.raises(InvalidArgument, match="federation loop") as refused:
            client.get("far", "location")
        # Refused at the first turn, not at the call's deadline.
        assert time.monotonic() - began < 4, refused.value
        # The gateways carry on: a bystander's Get answers.
        assert client.get("scout1", "location") == "(0 0 0 0 0 0)"
    with Client(b.address, timeout=8) as client, pytest.raises(InvalidArgument, match="federation loop"):
        client.get("back", "location")


def _until_both_are_up(client: Client, service: str) -> None:
    """The two gateways start one after the other: wait until a call reaches round the loop."""
    deadline = time.monotonic() + 20
    while True:
        try:
            client.get(service, "location")
        except Unavailable:
            assert time.monotonic() < deadline, "the other gateway never became reachable"
            time.sleep(0.2)
        except InvalidArgument:
            return


def test_a_gateway_naming_itself_is_refused_when_asked(gateway_process) -> None:  # type: ignore[no-untyped-def]
    # The registry refuses such a registration outright; a config may still name it: the first call says why.
    port = free_port()
    gw = gateway_process(
        f'[[services]]\nname = "me"\nurl = "grpc://127.0.0.1:{port}/me"\n',
        extra_args=("--listen", f"127.0.0.1:{port}"),
    )
    with Client(gw.address, timeout=8) as client, pytest.raises(InvalidArgument, match="federation loop"):
        client.get("me", "location")
