"""The C++ example client (clients/examples/cpp) against a real gateway process.

CMake generates the stubs from the .proto with protoc and grpc_cpp_plugin and links Debian's gRPC
C++ (libgrpc++-dev): a fourth gRPC stack, one contract. The build folder is build/cpp, kept between
runs: a second run only checks that nothing changed.
"""

from __future__ import annotations

from typing import Any

import pytest
from support.compiled_client import (
    BUILD_TIMEOUT,
    CompiledClient,
    build_cpp_client,
    check_an_unreachable_gateway_exits_3,
    check_errors_are_one_line_with_the_status_code,
    check_get_reads_what_the_python_stub_reads,
    check_listen_with_a_wildcard_prints_every_match_then_sync,
    check_session_reports_each_tagged_get_on_its_own_reply,
    check_set_is_seen_by_python_and_by_a_listen_until_sync,
)
from support.ports import free_port

# The first test of the session also carries the build: configure, then compile.
pytestmark = pytest.mark.timeout(2 * BUILD_TIMEOUT + 60)


@pytest.fixture(scope="session")
def cpp_client() -> CompiledClient:
    return build_cpp_client()


def test_get_reads_what_the_python_stub_reads(cpp_client: CompiledClient, demo_gateway: Any) -> None:
    check_get_reads_what_the_python_stub_reads(cpp_client, demo_gateway)


def test_set_is_seen_by_python_and_by_a_listen_until_sync(
    cpp_client: CompiledClient, demo_gateway: Any
) -> None:
    check_set_is_seen_by_python_and_by_a_listen_until_sync(cpp_client, demo_gateway)


def test_listen_with_a_wildcard_prints_every_match_then_sync(
    cpp_client: CompiledClient, demo_gateway: Any
) -> None:
    check_listen_with_a_wildcard_prints_every_match_then_sync(cpp_client, demo_gateway)


def test_session_reports_each_tagged_get_on_its_own_reply(
    cpp_client: CompiledClient, demo_gateway: Any
) -> None:
    check_session_reports_each_tagged_get_on_its_own_reply(cpp_client, demo_gateway)


def test_errors_are_one_line_with_the_status_code(cpp_client: CompiledClient, demo_gateway: Any) -> None:
    check_errors_are_one_line_with_the_status_code(cpp_client, demo_gateway)


def test_an_unreachable_gateway_exits_3(cpp_client: CompiledClient) -> None:
    check_an_unreachable_gateway_exits_3(cpp_client, free_port())
