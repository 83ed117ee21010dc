"""A Get whose path has ``*`` segments answers a snapshot of every match, as gNMI's Get does."""

from __future__ import annotations

import json

import grpc
import pytest
from support.gateway_process import GatewayProcess, StartGateway
from support.psctl import psctl

from clients.sync import Client
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

ROBOTS = ("scout1", "scout2", "rover1", "rover2")


def test_psctl_prints_every_match_as_path_value_lines(demo_gateway: GatewayProcess) -> None:
    done = psctl(demo_gateway.address, "get", "swarm", "robots.*.location")
    assert done.returncode == 0, done.stderr
    lines = dict(line.split(" = ") for line in done.stdout.splitlines())
    assert set(lines) == {f"robots.{name}.location" for name in ROBOTS}
    assert all(value.startswith("(") for value in lines.values())


def test_a_grpc_get_lists_matches_in_more_with_their_concrete_paths(demo_gateway: GatewayProcess) -> None:
    with grpc.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        response = stub.Get(
            pb.GetRequest(
                service="registry",
                property="services.*.state",
                more=[pb.PropertyRef(service="scout1", property="location")],
            ),
            timeout=30,
        )
    assert response.value == ""
    states = {v.property: v.value for v in response.more if v.service == "registry"}
    assert states["services.scout1.state"] == "up" and "services.rover2.state" in states
    assert [(v.service, v.property) for v in response.more][-1] == ("scout1", "location")


def test_the_sdk_and_json_output_read_the_same_snapshot(demo_gateway: GatewayProcess) -> None:
    with Client(demo_gateway.address) as client:
        matches = client.get_matching("swarm", "robots.*.location")
        with client.session() as session:
            assert set(session.get_matching("swarm", "robots.*.location")) == set(matches)
    done = psctl(demo_gateway.address, "--json", "get", "swarm", "robots.*.location")
    assert {row["property"] for row in json.loads(done.stdout)} == set(matches)


def test_a_pattern_that_matches_nothing_is_not_found(demo_gateway: GatewayProcess) -> None:
    done = psctl(demo_gateway.address, "get", "swarm", "robots.*.nothing")
    assert done.returncode == 1
    assert "NOT_FOUND" in done.stderr and "robots.*.nothing" in done.stderr


def test_more_matches_than_max_get_paths_is_resource_exhausted(gateway_process: StartGateway) -> None:
    gw = gateway_process("""
        [limits]
        max_get_paths = 3
        [[services]]
        name = "scout1"
        type = "sim-robot"
    """)
    with grpc.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.RpcError) as err:
            stub.Get(pb.GetRequest(service="registry", property="services.*.type.x"), timeout=30)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND
        with pytest.raises(grpc.RpcError) as err:
            stub.Get(pb.GetRequest(service="registry", property="services.*.*"), timeout=30)
    assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "at most 3 paths" in err.value.details()
