"""Client error classes: one per status code, readable text."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import grpc
import pytest
from support.ports import free_port

from clients.errors import (
    Cancelled,
    FailedPrecondition,
    GatewayUnreachable,
    NotFound,
    PropertyServiceError,
    Unavailable,
    Unknown,
    error_for_code,
    error_from_rpc,
)


@pytest.mark.parametrize("code", list(grpc.StatusCode))
def test_every_code_has_a_class_that_keeps_it(code: grpc.StatusCode) -> None:
    err = error_for_code(code, "why")
    assert isinstance(err, PropertyServiceError)
    assert err.code is code
    if code is not grpc.StatusCode.OK:
        assert type(err).__name__.lower() == code.name.replace("_", "").lower()


def test_numbers_as_in_session_replies() -> None:
    assert isinstance(error_for_code(5, "x"), NotFound)
    assert isinstance(error_for_code(9, "x"), FailedPrecondition)
    assert isinstance(error_for_code(1, "x"), Cancelled)
    unknown = error_for_code(999, "odd")
    assert isinstance(unknown, Unknown)
    assert unknown.code is grpc.StatusCode.UNKNOWN


def test_text_names_code_and_place() -> None:
    err = error_for_code(grpc.StatusCode.NOT_FOUND, 'unknown service "scoutX"', "scoutX", "location")
    assert str(err) == 'NOT_FOUND: unknown service "scoutX"'
    err = error_for_code(grpc.StatusCode.FAILED_PRECONDITION, "read-only", "scout1", "location")
    assert str(err) == "FAILED_PRECONDITION: read-only [scout1 location]"
    assert (err.service, err.property, err.message) == ("scout1", "location", "read-only")
    assert "FailedPrecondition(FAILED_PRECONDITION" in repr(err)


def test_unreachable_gateway_is_told_apart() -> None:
    target = f"127.0.0.1:{free_port()}"
    with grpc.insecure_channel(target) as channel:
        health = channel.unary_unary("/grpc.health.v1.Health/Check")
        with pytest.raises(grpc.RpcError) as refused:
            health(b"", timeout=5)
    err = error_from_rpc(refused.value, target=target)
    assert isinstance(err, GatewayUnreachable)
    assert isinstance(err, Unavailable)
    assert str(err).startswith(f"UNAVAILABLE: cannot reach the gateway at {target}")
    device = error_for_code(grpc.StatusCode.UNAVAILABLE, "scout7 is not answering")
    assert isinstance(device, Unavailable)
    assert not isinstance(device, GatewayUnreachable)


def test_a_gateway_that_answers_unavailable_for_what_lies_behind_it_was_reached() -> None:
    """The gateway's own words come first; grpc's about the connection come after them (an owner
    gateway, a device or etcd it could not reach): a service unavailable, not the gateway."""
    behind = (
        "thermo1 on gateway 127.0.0.1:13041: failed to connect to all addresses; last error: "
        "UNKNOWN: ipv4:127.0.0.1:13041: Failed to connect to remote host: Connection refused"
    )

    def refuse(_request: bytes, context: grpc.ServicerContext) -> bytes:
        context.abort(grpc.StatusCode.UNAVAILABLE, behind)

    handler = grpc.method_handlers_generic_handler(
        "propertyservice.v1.PropertyService", {"Get": grpc.unary_unary_rpc_method_handler(refuse)}
    )
    server = grpc.server(ThreadPoolExecutor(max_workers=1), handlers=[handler])
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    target = f"127.0.0.1:{port}"
    try:
        with grpc.insecure_channel(target) as channel:
            get = channel.unary_unary("/propertyservice.v1.PropertyService/Get")
            with pytest.raises(grpc.RpcError) as answered:
                get(b"", timeout=5)
    finally:
        server.stop(None)
    err = error_from_rpc(answered.value, "thermo1", "data", target=target)
    assert isinstance(err, Unavailable)
    assert not isinstance(err, GatewayUnreachable)
    assert str(err) == f"UNAVAILABLE: {behind}"
