"""Client-side value decoding and encoding: the text forms round-trip and bad text is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from clients.values import (
    Marker,
    ValueFormatError,
    format_value,
    parse_marker,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)


def test_number() -> None:
    assert parse_number("0.5") == 0.5
    assert parse_number(" -3e-2\n") == -0.03
    assert parse_number("2") == 2.0


@pytest.mark.parametrize("text", ["", "abc", "1,5", "nan", "inf", "1e999", "(1)", "1 2", "0x10", "1_000"])
def test_number_refuses(text: str) -> None:
    with pytest.raises(ValueFormatError, match="expected a number"):
        parse_number(text)


def test_vector() -> None:
    v = parse_vector("(1 2.5 -3e-2)")
    assert v.dtype == np.float64
    assert v.tolist() == [1.0, 2.5, -0.03]
    assert parse_vector("  ( 1   2 )  ").tolist() == [1.0, 2.0]
    assert parse_vector("()").shape == (0,)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("1 2 3", "missing parentheses"),
        ("(1 2", "unclosed"),
        ("(1, 2)", "not a number"),
        ("((1 2))", "numbers only"),
        ("(1 2) x", "after the closing"),
        ("(a b)", "not a number"),
        ("", "unclosed or empty"),
    ],
)
def test_vector_refuses(text: str, why: str) -> None:
    with pytest.raises(ValueFormatError, match=why):
        parse_vector(text)


def test_vectors_and_names() -> None:
    rows = parse_vectors("((1 2) (3 4 5))")
    assert [r.tolist() for r in rows] == [[1.0, 2.0], [3.0, 4.0, 5.0]]
    assert parse_vectors("()") == []
    assert parse_names("(a b.c scout1)") == ["a", "b.c", "scout1"]
    assert parse_names("()") == []
    with pytest.raises(ValueFormatError, match="not a vector"):
        parse_vectors("((1 2) 3)")
    with pytest.raises(ValueFormatError, match="not a name"):
        parse_names("(a (b))")


def test_marker() -> None:
    text = "<marker><location>(1 2)</location><color>(1 0 0)</color><name>a &amp; b</name></marker>"
    m = parse_marker(text)
    assert m.tag == "marker"
    assert m.location is not None
    assert m.location.tolist() == [1.0, 2.0]
    assert m.vector("color").tolist() == [1.0, 0.0, 0.0]
    assert m.fields["name"] == "a & b"
    assert parse_marker(m.to_xml()) == m
    assert parse_marker("<marker/>") == Marker()
    assert Marker().location is None


def test_nested_marker_round_trips() -> None:
    text = "<marker><target><location>(1 2)</location></target><id>7</id></marker>"
    m = parse_marker(text)
    target = m.fields["target"]
    assert isinstance(target, Marker)
    assert target.location is not None
    assert target.location.tolist() == [1.0, 2.0]
    assert m.to_xml() == text


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("<marker><location>(1 2)</location>", "not well-formed"),
        ('<!DOCTYPE m [<!ENTITY x "y">]><marker>&x;</marker>', "expected a marker"),
        ('<marker a="1"/>', "attributes"),
        ("<marker>text<location>(1)</location></marker>", "mixes text"),
        ("<marker><a>1</a><a>2</a></marker>", "more than one"),
        ("<marker>hello</marker>", "must hold fields"),
        ("not xml", "not well-formed"),
    ],
)
def test_marker_refuses(text: str, why: str) -> None:
    with pytest.raises(ValueFormatError, match=why):
        parse_marker(text)


def test_marker_at_formats_fields() -> None:
    m = Marker.at([2, 1, 0, 0, 0, 0], color=(1, 0, 0), speed=0.5)
    assert m.to_xml() == (
        "<marker><location>(2 1 0 0 0 0)</location><color>(1 0 0)</color><speed>0.5</speed></marker>"
    )


def test_format_value() -> None:
    assert format_value("as is (x") == "as is (x"
    assert format_value(True) == "true"
    assert format_value(np.bool_(False)) == "false"
    assert format_value(2.0) == "2"
    assert format_value(0.1) == "0.1"
    assert format_value(np.float32(0.5)) == "0.5"
    assert format_value(7) == "7"
    assert format_value(np.array([2.0, 1.0, 0.25])) == "(2 1 0.25)"
    assert format_value([1, 2.5]) == "(1 2.5)"
    assert format_value(np.array([[1, 2], [3, 4]])) == "((1 2) (3 4))"
    assert format_value(["a", "b"]) == "(a b)"
    assert format_value(Marker.at((1, 2))) == "<marker><location>(1 2)</location></marker>"


def test_format_value_refuses() -> None:
    with pytest.raises(ValueFormatError, match="finite"):
        format_value(math.nan)
    with pytest.raises(ValueFormatError, match="without spaces"):
        format_value(["a b"])
    with pytest.raises(ValueFormatError, match="shape"):
        format_value(np.zeros((2, 2, 2)))
    with pytest.raises(TypeError, match="no value format"):
        format_value(object())


_finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@given(st.lists(_finite, max_size=12))
def test_vector_round_trip(xs: list[float]) -> None:
    assert parse_vector(format_value(np.array(xs, dtype=np.float64))).tolist() == xs


@given(_finite)
def test_number_round_trip(x: float) -> None:
    assert parse_number(format_value(x)) == x


def test_the_client_reads_values_with_the_services_grammar() -> None:
    from services.kernel import values as grammar

    assert parse_vector is grammar.parse_vector
    assert Marker is grammar.Marker
    assert ValueFormatError is grammar.ValueFormatError
    with pytest.raises(ValueError, match="expected a vector"):  # what the SDK documents
        parse_vector("(1 x)")
