"""The C++ and Go clients print the same bytes for the same answers: quotes, newlines and
markers' angle brackets escaped alike (docs/client.md promises one output format)."""

from __future__ import annotations

from typing import Any

import pytest
from support.compiled_client import BUILD_TIMEOUT, build_cpp_client, build_go_client

pytestmark = pytest.mark.timeout(3 * BUILD_TIMEOUT + 60)


def test_cpp_and_go_print_the_same_lines(demo_gateway: Any) -> None:
    cpp, go = build_cpp_client(), build_go_client()
    calls = [
        ("get", "missions", "patrol.definition"),  # an SCXML document: quotes, newlines, <>
        ("listen", "*", "location.x"),
        ("session", "scout2:location", "nosuch:location"),
        ("get", "scoutX", "location"),
    ]
    for call in calls:
        by_cpp, by_go = cpp.run(demo_gateway.address, *call), go.run(demo_gateway.address, *call)
        assert by_cpp.stdout or by_cpp.stderr, call
        assert (by_cpp.returncode, by_cpp.stdout, by_cpp.stderr) == (
            by_go.returncode,
            by_go.stdout,
            by_go.stderr,
        ), call
    for asked in ("-h", "--help"):  # the usage on stdout, exit 0; no "unknown command"
        by_cpp, by_go = cpp.run(demo_gateway.address, asked), go.run(demo_gateway.address, asked)
        assert (by_cpp.returncode, by_cpp.stderr) == (0, "") and by_cpp.stdout.startswith("usage: propctl")
        assert (by_go.returncode, by_go.stdout, by_go.stderr) == (0, by_cpp.stdout, ""), asked
