"""The Go example client (clients/examples/go) against a real gateway process.

It is built offline from Debian's Go sources (GOPATH mode, clients/examples/go/build.sh) with
stubs that protoc-gen-go and protoc-gen-go-grpc generate from the .proto: a third gRPC stack
(grpc-go), one contract. The build folder is build/go; its Go build cache makes a second run fast.
"""

from __future__ import annotations

from typing import Any

import pytest
from support.compiled_client import (
    BUILD_TIMEOUT,
    CompiledClient,
    build_go_client,
    check_an_unreachable_gateway_exits_3,
    check_errors_are_one_line_with_the_status_code,
    check_get_reads_what_the_python_stub_reads,
    check_listen_with_a_wildcard_prints_every_match_then_sync,
    check_session_reports_each_tagged_get_on_its_own_reply,
    check_set_is_seen_by_python_and_by_a_listen_until_sync,
)
from support.ports import free_port

# The first test of the session also carries the build.
pytestmark = pytest.mark.timeout(BUILD_TIMEOUT + 60)


@pytest.fixture(scope="session")
def go_client() -> CompiledClient:
    return build_go_client()


def test_get_reads_what_the_python_stub_reads(go_client: CompiledClient, demo_gateway: Any) -> None:
    check_get_reads_what_the_python_stub_reads(go_client, demo_gateway)


def test_set_is_seen_by_python_and_by_a_listen_until_sync(
    go_client: CompiledClient, demo_gateway: Any
) -> None:
    check_set_is_seen_by_python_and_by_a_listen_until_sync(go_client, demo_gateway)


def test_listen_with_a_wildcard_prints_every_match_then_sync(
    go_client: CompiledClient, demo_gateway: Any
) -> None:
    check_listen_with_a_wildcard_prints_every_match_then_sync(go_client, demo_gateway)


def test_session_reports_each_tagged_get_on_its_own_reply(
    go_client: CompiledClient, demo_gateway: Any
) -> None:
    check_session_reports_each_tagged_get_on_its_own_reply(go_client, demo_gateway)


def test_errors_are_one_line_with_the_status_code(go_client: CompiledClient, demo_gateway: Any) -> None:
    check_errors_are_one_line_with_the_status_code(go_client, demo_gateway)


def test_an_unreachable_gateway_exits_3(go_client: CompiledClient) -> None:
    check_an_unreachable_gateway_exits_3(go_client, free_port())
