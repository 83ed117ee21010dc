"""gateway.options: options declared on a dataclass's fields, read from a config table or a URL."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from gateway.options import Bounds, Wording, option, read_options, url_options
from gateway.proxies.grpc_proxy import GrpcProxyOptions
from gateway.proxies.line_proxy import ProxyOptions
from services.kernel.errors import InvalidArgument


@dataclass(frozen=True, slots=True)
class Knobs:
    """A section with one option of each kind."""

    name: str = "a"
    on: bool = False
    count: int = option(3, low=1)
    share: float = 0.5
    wait: float = option(2.0, above=True, unit="seconds")
    period: float = option(15.0, low=0.5, high=60.0, off=0, unit="seconds")


IN_A_FILE = Wording(
    unknown="{where}.{key}: unknown key (known: {known})", bad="{where}.{key}: {why}, got {raw}"
)
IN_A_URL = Wording(unknown="unknown option {key!r} (known: {known})", bad="bad option {key}={raw}: {why}")


def test_a_table_of_good_values_is_taken_as_typed() -> None:
    values, problems = read_options(
        Knobs, {"name": "b", "on": True, "count": 2, "share": 1, "period": 0}, IN_A_FILE, where="knobs"
    )
    assert problems == []
    assert Knobs(**values) == Knobs(name="b", on=True, count=2, share=1.0, period=0.0)
    assert isinstance(values["share"], float)


def test_every_bad_key_of_a_table_is_named_with_what_it_takes_and_the_good_ones_are_kept() -> None:
    given = {"colour": 1, "on": 1, "count": True, "share": -1, "wait": 0, "period": 0.1, "name": "kept"}
    values, problems = read_options(Knobs, given, IN_A_FILE, where="site.toml: knobs")
    assert problems == [
        "site.toml: knobs.colour: unknown key (known: name, on, count, share, wait, period)",
        "site.toml: knobs.on: expected true or false, got 1",
        "site.toml: knobs.count: expected an integer, got True",
        "site.toml: knobs.share: must not be negative, got -1",
        "site.toml: knobs.wait: must be a positive number of seconds, got 0",
        "site.toml: knobs.period: must be from 0.5 to 60 seconds (or 0: off), got 0.1",
    ]
    assert values == {"name": "kept"}


def test_a_table_is_typed_already_so_text_is_not_a_number_there() -> None:
    _, problems = read_options(Knobs, {"count": "2"}, IN_A_FILE, where="knobs")
    assert problems == ["knobs.count: expected an integer, got '2'"]


def test_text_from_a_url_is_read_as_the_field_type() -> None:
    given = {"on": "yes", "count": "7", "share": "0.25", "period": "30"}
    values, problems = read_options(Knobs, given, IN_A_URL, text=True)
    assert problems == []
    assert values == {"on": True, "count": 7, "share": 0.25, "period": 30.0}
    _, problems = read_options(Knobs, {"on": "maybe", "count": "1.5", "share": "nan"}, IN_A_URL, text=True)
    assert problems == [
        "bad option on='maybe': expected true or false",
        "bad option count='1.5': expected an integer",
        "bad option share='nan': must be a finite number",
    ]


def test_keys_read_elsewhere_are_skipped_and_named_among_the_known() -> None:
    values, problems = read_options(
        Knobs, {"baudrate": "9600", "colour": "red"}, IN_A_URL, text=True, skip=["baudrate"]
    )
    assert values == {}
    assert problems == ["unknown option 'colour' (known: name, on, count, share, wait, period, baudrate)"]


def test_a_long_value_is_cut_in_the_message() -> None:
    _, problems = read_options(Knobs, {"count": "x" * 400}, IN_A_URL, text=True)
    assert problems == [f"bad option count={'x' * 40!r}: expected an integer"]


@pytest.mark.parametrize(
    ("bounds", "value", "why"),
    [
        (Bounds(), -1, "must not be negative"),
        (Bounds(), math.inf, "must be a finite number"),
        (Bounds(unit="seconds"), math.nan, "must be a finite number of seconds"),
        (Bounds(low=1), 0, "must be at least 1"),
        (Bounds(above=True), 0, "must be a positive number"),
        (Bounds(above=True), math.inf, "must be a positive number"),
        (Bounds(above=True, unit="seconds"), math.inf, "must be a positive number of seconds"),
        (Bounds(above=True, high=3600, unit="seconds"), 3601, "must be more than 0 and at most 3600 seconds"),
        (Bounds(low=1, high=4096), 5000, "must be from 1 to 4096"),
    ],
)
def test_what_a_number_must_be_is_said_from_its_bounds(bounds: Bounds, value: float, why: str) -> None:
    assert bounds.problem(value) == why


def test_a_number_within_its_bounds_or_at_off_has_no_problem() -> None:
    assert Bounds(low=0.5, high=60, off=0).problem(0) is None
    assert Bounds(low=0.5, high=60, off=0).problem(60) is None
    assert Bounds(above=True).problem(1e-9) is None


def test_the_options_of_a_url_query_are_overridden_by_the_config_entry() -> None:
    assert url_options("tcp://h:1?timeout=2&checksum=1", {"timeout": 3}) == {"timeout": 3, "checksum": "1"}


def test_a_line_proxy_takes_its_options_from_the_url_and_refuses_them_out_of_bounds() -> None:
    options = ProxyOptions.parse("tcp://127.0.0.1:7001?keepalive=0&checksum=on", {"max_in_flight": 8})
    assert (options.keepalive, options.checksum, options.max_in_flight) == (0.0, True, 8)
    for query, said in (
        (
            "keepalive=0.001",
            "bad proxy option keepalive='0.001': must be from 0.5 to 3600 seconds (or 0: off)",
        ),
        ("timeout=1e300", "bad proxy option timeout='1e300': must be from 0.01 to 600 seconds"),
        ("max_in_flight=100000", "bad proxy option max_in_flight='100000': must be from 1 to 4096"),
        ("checksum=perhaps", "bad proxy option checksum='perhaps': expected true or false"),
        ("colour=red", "unknown proxy option 'colour' (known: timeout, connect_timeout"),
    ):
        with pytest.raises(InvalidArgument) as info:
            ProxyOptions.parse(f"tcp://127.0.0.1:7001?{query}", {})
        assert info.value.message.startswith(said), info.value.message


def test_a_grpc_proxy_takes_positive_seconds_and_names_its_tls_files_among_the_known() -> None:
    options = GrpcProxyOptions.parse("grpc://127.0.0.1:5000/scout1?timeout=0.5", {"backoff_max": 2})
    assert (options.timeout, options.backoff_max) == (0.5, 2.0)
    with pytest.raises(InvalidArgument) as info:
        GrpcProxyOptions.parse("grpc://127.0.0.1:5000/scout1?timeout=0", {})
    assert info.value.message == "bad grpc proxy option timeout='0': must be a positive number of seconds"
    with pytest.raises(InvalidArgument) as info:
        GrpcProxyOptions.parse("grpc://127.0.0.1:5000/scout1", {"colour": "red"})
    assert info.value.message.endswith(
        "(known: timeout, connect_timeout, backoff_initial, backoff_max, ca, cert, key)"
    )
