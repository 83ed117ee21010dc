"""The addresses a client is given, and which one it uses after a failure."""

from __future__ import annotations

import pytest

from clients.aio.gateways import GatewayList, channel_options, parse_targets


def test_a_comma_separated_string_names_several_gateways() -> None:
    assert parse_targets("gw1:50051, gw2:50051,") == ("gw1:50051", "gw2:50051")
    assert parse_targets(["gw1:50051", "gw2:50051"]) == ("gw1:50051", "gw2:50051")
    assert parse_targets("127.0.0.1:50051") == ("127.0.0.1:50051",)


def test_a_grpc_name_with_a_scheme_is_one_target_whatever_its_commas() -> None:
    assert parse_targets("ipv4:10.0.0.1:50051,10.0.0.2:50051") == ("ipv4:10.0.0.1:50051,10.0.0.2:50051",)
    assert parse_targets("dns:///gateways.example:50051") == ("dns:///gateways.example:50051",)


@pytest.mark.parametrize("bad", ["", " , ", [], ["gw1:50051", "gw 2:50051"]])
def test_no_address_or_a_blank_in_one_is_a_clear_error(bad: str | list[str]) -> None:
    with pytest.raises(ValueError, match="address"):
        parse_targets(bad)


def test_a_failure_moves_to_the_next_address_and_round_the_list() -> None:
    gateways = GatewayList("a:1,b:2,c:3")
    assert gateways.current == "a:1"
    assert gateways.move_on("a:1")
    assert gateways.current == "b:2"
    assert gateways.move_on("b:2") and gateways.move_on("c:3")
    assert gateways.current == "a:1"


def test_a_failure_reported_late_by_a_call_on_an_address_already_left_moves_nothing() -> None:
    gateways = GatewayList(["a:1", "b:2", "c:3"])
    assert gateways.move_on("a:1")
    # A second stream that broke on a:1 with the first reports it now: the client stays on b:2.
    assert not gateways.move_on("a:1")
    assert gateways.current == "b:2"


def test_one_address_has_nowhere_to_move() -> None:
    gateways = GatewayList("a:1")
    assert not gateways.move_on("a:1")
    assert gateways.current == "a:1"


def test_keepalive_pings_while_calls_are_open_and_never_stop_on_a_quiet_stream() -> None:
    options = dict(channel_options(1.5))
    assert options["grpc.keepalive_time_ms"] == 1500
    assert options["grpc.keepalive_timeout_ms"] == 1500
    assert options["grpc.http2.max_pings_without_data"] == 0
    assert "grpc.keepalive_permit_without_calls" not in options
    assert channel_options(None) == []
