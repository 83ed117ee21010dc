"""Client error classes: one per status code, readable text."""

from __future__ import annotations

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
