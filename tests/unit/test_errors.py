"""The one error table: every status code has its class, and every part picks it the same way."""

from __future__ import annotations

import grpc
import pytest

from clients import errors as client_errors
from gateway.engine.status import to_property_error
from gateway.fronts.grpc_v1.status import GRPC_STATUS, error_from_status
from services.kernel import errors
from services.kernel.errors import Code, NotFound, PropertyError, ReadOnly, error_for
from services.kernel.line_protocol import ErrorReply, decode_line


@pytest.mark.parametrize("code", [c for c in Code if c is not Code.OK])
def test_every_failure_code_has_its_own_class(code: Code) -> None:
    err = error_for(code, "why")
    assert type(err) is errors.ERROR_CLASSES[code]
    assert type(err).__name__.lower() == code.name.replace("_", "").lower()
    assert (err.code, err.message) == (code, "why")
    assert error_for(int(code), "why").code is code


def test_numbers_no_code_has_become_unknown() -> None:
    err = error_for(77, "odd")
    assert isinstance(err, errors.Unknown) and err.code is Code.UNKNOWN


def test_read_only_is_a_failed_precondition() -> None:
    assert isinstance(ReadOnly("x"), errors.FailedPrecondition)
    assert ReadOnly("x").code is Code.FAILED_PRECONDITION


def test_an_err_line_raises_the_class_of_its_code() -> None:
    reply = decode_line(b"ERR 5 no such property")
    assert isinstance(reply, ErrorReply)
    err = reply.to_exception("device d1")
    assert isinstance(err, NotFound)
    assert err.message == "device d1: no such property"


def test_a_remote_status_becomes_the_class_of_its_code() -> None:
    for code, status in GRPC_STATUS.items():
        err = error_from_status(status, "remote says")
        assert type(err) is errors.error_class(code) and err.code is code


def test_an_unexpected_exception_becomes_internal() -> None:
    err = to_property_error(ValueError("boom"), "get x")
    assert isinstance(err, errors.Internal)
    assert err.message == "internal error in get x: ValueError"
    passed = NotFound("x")
    assert to_property_error(passed) is passed


def test_the_client_classes_follow_the_same_table() -> None:
    for code, cls in errors.ERROR_CLASSES.items():
        err = client_errors.error_for_code(int(code), "m")
        assert type(err).__name__ == cls.__name__
        assert err.code is GRPC_STATUS[code]
    assert client_errors.error_for_code(grpc.StatusCode.OK, "m").code is grpc.StatusCode.OK
    assert not isinstance(client_errors.error_for_code(5, "m"), PropertyError)
