"""A doc page's shell block that shows each command's output as comments below it, read as steps."""

from __future__ import annotations

from support.walkthrough import commented_steps

BLOCK = """\
grpcurl -plaintext -H 'x-request-id: mission-7' \\
    -d '{"service":"rover1"}' 127.0.0.1:50051 grpc.health.v1.Health/Check
# {
#   "status": "SERVING"
# }

jq -cR 'fromjson?' gateway.log     # everything
#  an indented line
grpc_health_probe -addr=127.0.0.1:50051
"""


def test_a_continued_line_is_one_command_and_the_comments_below_it_its_output() -> None:
    assert commented_steps(BLOCK) == [
        (
            "grpcurl -plaintext -H 'x-request-id: mission-7' -d '{\"service\":\"rover1\"}' 127.0.0.1:50051 "
            "grpc.health.v1.Health/Check",
            ["{", '  "status": "SERVING"', "}"],
        ),
        ("jq -cR 'fromjson?' gateway.log", [" an indented line"]),
        ("grpc_health_probe -addr=127.0.0.1:50051", []),
    ]


def test_comments_before_any_command_are_no_ones_output() -> None:
    assert commented_steps("# start the gateway first\npsctl get scout1 location\n") == [
        ("psctl get scout1 location", [])
    ]
