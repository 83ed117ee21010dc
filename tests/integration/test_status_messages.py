"""What an error says: names as the user wrote them, and never more than a bounded message."""

from __future__ import annotations

import grpc
import pytest
from support.gateway_process import GatewayProcess
from support.psctl import psctl

from gateway.engine.status import MAX_MESSAGE_CHARS
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc


def test_a_non_ascii_name_shows_as_itself(demo_gateway: GatewayProcess) -> None:
    done = psctl(demo_gateway.address, "get", "scout1", "lôcation")
    assert done.returncode == 1
    assert 'bad property path "lôcation"' in done.stderr
    assert "\\x" not in done.stderr and "\\u" not in done.stderr


def test_thousands_of_parameters_are_invalid_argument_with_a_short_message(
    demo_gateway: GatewayProcess,
) -> None:
    params = {f"p{i:05d}": "1" for i in range(3000)}
    with grpc.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.RpcError) as err:
            stub.Get(pb.GetRequest(service="scout1", property="location", parameters=params), timeout=30)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    message = err.value.details()
    assert "takes no parameters" in message and "and 2995 more" in message
    assert len(message) <= MAX_MESSAGE_CHARS


def test_psctl_shows_invalid_argument_not_resource_exhausted(demo_gateway: GatewayProcess) -> None:
    params = [arg for i in range(3000) for arg in ("-p", f"p{i:05d}=1")]
    done = psctl(demo_gateway.address, "get", "scout1", "location", *params)
    assert done.returncode == 1
    assert "INVALID_ARGUMENT" in done.stderr and "RESOURCE_EXHAUSTED" not in done.stderr


def test_a_service_that_echoes_every_name_is_clipped_to_the_bound(demo_gateway: GatewayProcess) -> None:
    # The group names each stranger it was asked to take: 3,000 names are over 20 KB, more than
    # the 16 KiB a grpc trailer may hold; clipped, the caller sees the service's own answer.
    strangers = " ".join(f"nobody{i:05d}" for i in range(3000))
    with grpc.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.RpcError) as err:
            stub.Set(
                pb.SetRequest(
                    service="swarm",
                    property="subgroup",
                    value="team",
                    parameters={"members": f"({strangers})"},
                ),
                timeout=30,
            )
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    message = err.value.details()
    assert message.startswith("not members of this group: nobody00000 nobody00001")
    assert len(message) <= MAX_MESSAGE_CHARS and message.endswith("more characters)")
