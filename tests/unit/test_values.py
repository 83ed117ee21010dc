"""Value formats: round trips, strictness, clear errors, hostile XML."""

from __future__ import annotations

import math
from typing import Annotated, Any, Optional

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.kernel.errors import Code, InvalidArgument, NotFound
from services.kernel.values import (
    MAX_LIST_DEPTH,
    MAX_VALUE_LENGTH,
    Marker,
    ValueFormatError,
    Vector,
    format_bool,
    format_list,
    format_marker,
    format_names,
    format_number,
    format_value,
    format_vector,
    format_vectors,
    parse_as,
    parse_bool,
    parse_int,
    parse_list,
    parse_marker,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
    parser_for,
    type_name,
    vector_index,
)

finite = st.floats(allow_nan=False, allow_infinity=False)
# List atoms: anything but whitespace (as str.isspace and re's \s define it) and parentheses.
atoms = st.text(
    st.characters(exclude_categories=("Cs",), exclude_characters="()").filter(lambda c: not c.isspace()),
    min_size=1,
    max_size=12,
)
nested_lists = st.recursive(atoms, lambda inner: st.lists(inner, max_size=5), max_leaves=30)
_LETTERS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ_"
tags = st.builds(str.__add__, st.sampled_from(_LETTERS), st.text(_LETTERS + "0123456789-", max_size=20))
# Characters XML 1.0 can carry (section 2.2): no other C0 controls, no surrogates, not U+FFFE/U+FFFF.
xml_text = st.text(
    st.characters(
        blacklist_categories=("Cs",),
        blacklist_characters=[chr(c) for c in range(32) if chr(c) not in "\t\n\r"] + ["\ufffe", "\uffff"],
    )
)
marker_trees = st.recursive(xml_text, lambda inner: st.dictionaries(tags, inner, min_size=1, max_size=4))


def as_marker(tag: str, tree: dict[str, Any]) -> Marker:
    return Marker(tag, {k: as_marker(k, v) if isinstance(v, dict) else v for k, v in tree.items()})


markers = st.builds(as_marker, tags, st.dictionaries(tags, marker_trees, max_size=5))
PARSERS = [
    parse_number,
    parse_int,
    parse_bool,
    parse_vector,
    parse_list,
    parse_vectors,
    parse_names,
    parse_marker,
]


def test_value_format_error_is_invalid_argument() -> None:
    with pytest.raises(InvalidArgument) as info:
        parse_number("abc")
    assert info.value.code == Code.INVALID_ARGUMENT


# --- numbers ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "value"),
    [("0.5", 0.5), ("-3", -3.0), ("1e-3", 0.001), ("+2.", 2.0), (".25", 0.25), (" 7 ", 7.0), ("1E2", 100.0)],
)
def test_parse_number(text: str, value: float) -> None:
    assert parse_number(text) == value


@pytest.mark.parametrize(
    ("x", "text"),
    [
        (2.0, "2"),
        (0.5, "0.5"),
        (-0.03, "-0.03"),
        (1e20, "1e+20"),
        (1e-7, "1e-07"),
        (3, "3"),
        (np.float32(0.5), "0.5"),
    ],
)
def test_format_number(x: float, text: str) -> None:
    assert format_number(x) == text


@given(finite)
def test_number_round_trip(x: float) -> None:
    assert parse_number(format_number(x)) == x


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("nan", '"nan" is not a finite number'),
        ("-Infinity", "not a finite number"),
        ("1e999", "too large"),
        ("1,5", "decimal point"),
        ("", "empty"),
        ("1_000", '"1_000" is not a number'),
        ("0x10", "not a number"),
        ("١٢", "not a number"),
    ],
)
def test_parse_number_refuses(text: str, message: str) -> None:
    with pytest.raises(ValueFormatError, match="expected a number") as info:
        parse_number(text)
    assert message in info.value.message


@pytest.mark.parametrize("x", [math.nan, math.inf, -math.inf])
def test_format_number_refuses_non_finite(x: float) -> None:
    with pytest.raises(ValueFormatError, match="finite"):
        format_number(x)


def test_parse_int() -> None:
    assert parse_int("42") == 42
    assert parse_int(" -7\n") == -7
    with pytest.raises(ValueFormatError, match="fraction"):
        parse_int("4.5")
    with pytest.raises(ValueFormatError, match='"x" is not an integer'):
        parse_int("x")
    with pytest.raises(ValueFormatError, match="too many digits"):
        parse_int("9" * 10000)


@given(st.integers())
def test_int_round_trip(n: int) -> None:
    assert parse_int(format_number(n)) == n


@pytest.mark.parametrize("word", ["true", "TRUE", "1", "on", "Yes"])
def test_parse_bool_true(word: str) -> None:
    assert parse_bool(word) is True


@pytest.mark.parametrize("word", ["false", "False", "0", "OFF", "no"])
def test_parse_bool_false(word: str) -> None:
    assert parse_bool(word) is False


def test_bool_round_trip_and_refusal() -> None:
    assert parse_bool(format_bool(True)) is True
    assert parse_bool(format_bool(False)) is False
    with pytest.raises(ValueFormatError, match=r'expected a boolean \("true" or "false"\), got "maybe"'):
        parse_bool("maybe")


# --- vectors ---------------------------------------------------------------


def test_parse_vector() -> None:
    v = parse_vector("(1 2.5 -3e-2)")
    assert v.dtype == np.float64
    assert v.tolist() == [1.0, 2.5, -0.03]
    assert format_vector(v) == "(1 2.5 -0.03)"
    assert parse_vector("()").shape == (0,)
    assert parse_vector(" ( 1\t2\n) ").tolist() == [1.0, 2.0]


@given(st.lists(finite, max_size=20))
def test_vector_round_trip(xs: list[float]) -> None:
    v = np.array(xs, dtype=np.float64)
    back = parse_vector(format_vector(v))
    assert back.dtype == np.float64
    assert np.array_equal(back, v)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("(1 2 x)", 'expected a vector like "(1 2 3)", got "(1 2 x)": "x" is not a number'),
        ("(1, 2, 3)", "separate the numbers with spaces, not commas"),
        ("1 2 3", "enclosed in parentheses"),
        ("(1 2", "enclosed in parentheses"),
        ("((1 2))", "not nested lists"),
        ("(1 nan)", '"nan" is not a finite number'),
        ("", "empty"),
    ],
)
def test_parse_vector_refuses(text: str, message: str) -> None:
    with pytest.raises(ValueFormatError) as info:
        parse_vector(text)
    assert message in info.value.message


def test_error_message_clips_long_text() -> None:
    with pytest.raises(ValueFormatError) as info:
        parse_vector("(" + "1 " * 5000 + "x)")
    assert len(info.value.message) < 200
    assert "…" in info.value.message


def test_format_vector_refuses_2d() -> None:
    with pytest.raises(ValueFormatError, match="1-D"):
        format_vector(np.zeros((2, 2)))


# --- lists, vectors, names -------------------------------------------------


def test_parse_list() -> None:
    assert parse_list("((1 2) (3 4))") == [["1", "2"], ["3", "4"]]
    assert parse_list("(a b (c 1))") == ["a", "b", ["c", "1"]]
    assert parse_list("()") == []
    assert parse_list(" (a(b)c) ") == ["a", ["b"], "c"]


@given(st.lists(nested_lists, max_size=6))
def test_list_round_trip(items: list[Any]) -> None:
    assert parse_list(format_list(items)) == items


def test_format_list_mixed() -> None:
    assert format_list([[1, 2.5], ("a", [True]), np.array([0.5, 2.0])]) == "((1 2.5) (a (true)) (0.5 2))"
    with pytest.raises(ValueFormatError, match="without spaces or parentheses"):
        format_list(["two words"])
    with pytest.raises(ValueFormatError, match="without spaces"):
        format_list([""])
    with pytest.raises(ValueFormatError, match="dict"):
        format_list([{}])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("(a b", 'unclosed "("'),
        ("(a))", "after the end of the list"),
        (")", 'unmatched ")" at position 0'),
        ("a b", "enclosed in parentheses"),
        ("  ", "empty"),
        ("(a) (b)", "after the end"),
    ],
)
def test_parse_list_refuses(text: str, message: str) -> None:
    with pytest.raises(ValueFormatError) as info:
        parse_list(text)
    assert message in info.value.message


def test_list_depth_limit() -> None:
    ok = "(" * MAX_LIST_DEPTH + ")" * MAX_LIST_DEPTH
    assert parse_list(ok) is not None
    deep = "(" * (MAX_LIST_DEPTH + 1) + ")" * (MAX_LIST_DEPTH + 1)
    with pytest.raises(ValueFormatError, match=f"deeper than {MAX_LIST_DEPTH}"):
        parse_list(deep)
    with pytest.raises(ValueFormatError, match="deeper"):
        format_list(_nest(MAX_LIST_DEPTH + 1))
    assert format_list(_nest(MAX_LIST_DEPTH)) == ok


def _nest(depth: int) -> list[Any]:
    value: list[Any] = []
    for _ in range(depth - 1):
        value = [value]
    return value


@pytest.mark.parametrize("parser", PARSERS)
def test_length_limit(parser: Any) -> None:
    with pytest.raises(ValueFormatError, match=f"the limit is {MAX_VALUE_LENGTH} characters"):
        parser("(" + "1 " * MAX_VALUE_LENGTH + ")")


def test_vectors() -> None:
    vs = parse_vectors("((1.0 0.0) (2.0 0.1))")
    assert [v.tolist() for v in vs] == [[1.0, 0.0], [2.0, 0.1]]
    assert format_vectors(vs) == "((1 0) (2 0.1))"
    assert format_vectors(np.array([[1.0, 2.0], [3.0, 4.0]])) == "((1 2) (3 4))"
    assert parse_vectors("()") == []
    with pytest.raises(ValueFormatError, match=r'expected a list of vectors.*item 2 \("3"\) is not a vector'):
        parse_vectors("((1 2) 3)")
    with pytest.raises(ValueFormatError, match='in vector 1: "a" is not a number'):
        parse_vectors("((1 a))")
    with pytest.raises(ValueFormatError, match="expected a list of vectors"):
        parse_vectors("((1 2)")


@given(st.lists(st.lists(finite, max_size=6), max_size=6))
def test_vectors_round_trip(rows: list[list[float]]) -> None:
    vs = [np.array(r, dtype=np.float64) for r in rows]
    back = parse_vectors(format_vectors(vs))
    assert len(back) == len(vs)
    assert all(np.array_equal(a, b) for a, b in zip(back, vs, strict=True))


def test_names() -> None:
    assert parse_names("(location velocity behaviors.moveto)") == ["location", "velocity", "behaviors.moveto"]
    assert format_names(["a", "b.c"]) == "(a b.c)"
    assert format_names(iter(())) == "()"
    with pytest.raises(ValueFormatError, match="item 2 is a nested list"):
        parse_names("(a (b))")
    with pytest.raises(ValueFormatError, match="expected a list of names"):
        parse_names("a")
    with pytest.raises(ValueFormatError):
        format_names(["a b"])


@given(st.lists(atoms, max_size=10))
def test_names_round_trip(names: list[str]) -> None:
    assert parse_names(format_names(names)) == names


# --- markers ---------------------------------------------------------------

MARKER = "<marker><location>(1.0 0.1)</location><color>(1 0 0)</color></marker>"


def test_parse_marker() -> None:
    m = parse_marker(MARKER)
    assert m.tag == "marker"
    assert list(m.fields) == ["location", "color"]
    assert m.fields["color"] == "(1 0 0)"
    location = m.location
    assert location is not None
    assert location.tolist() == [1.0, 0.1]
    assert format_marker(m) == MARKER


def test_marker_nested_get_and_with_field() -> None:
    m = parse_marker(
        '<?xml version="1.0"?>\n<target>\n  <pose><location>(1 2)</location></pose>\n'
        "  <name>a &amp; b</name><!-- a comment -->\n</target>"
    )
    assert m.tag == "target"
    assert m.get("pose.location") == "(1 2)"
    assert m.get("pose") == "<pose><location>(1 2)</location></pose>"
    assert m.get("name") == "a & b"
    assert m.location is None
    with pytest.raises(NotFound, match="no field 'speed'"):
        m.get("speed")
    with pytest.raises(NotFound, match="'pose' of the marker has no field 'x'"):
        m.get("pose.x")
    with pytest.raises(NotFound):
        m.get("name.x")
    m2 = m.with_field("location", np.array([3.0, 4.5])).with_field("name", "c")
    assert m2.location is not None
    assert m2.location.tolist() == [3.0, 4.5]
    assert list(m2.fields) == ["pose", "name", "location"]
    assert m.get("name") == "a & b"  # the original is unchanged
    assert format_marker(m2) == (
        "<target><pose><location>(1 2)</location></pose><name>c</name><location>(3 4.5)</location></target>"
    )
    with pytest.raises(ValueFormatError):
        m.with_field("bad name", "x")


def test_empty_marker() -> None:
    assert parse_marker("<marker/>") == Marker("marker", {})
    assert parse_marker("<marker>  </marker>") == Marker("marker", {})
    assert format_marker(Marker()) == "<marker></marker>"


@given(markers)
def test_marker_round_trip(m: Marker) -> None:
    assert parse_marker(format_marker(m)) == m


def test_marker_escaping() -> None:
    m = Marker("m", {"t": "<a> & </b> ]]> \r\n \"q\" 'q'"})
    text = format_marker(m)
    assert "<a>" not in text
    assert parse_marker(text) == m


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('<marker a="1"><x>1</x></marker>', "has attributes"),
        ("<marker>text<x>1</x></marker>", "mixes text"),
        ("<marker><x>1</x>tail</marker>", "mixes text"),
        ("<marker><x>1</x><x>2</x></marker>", "more than one <x>"),
        ("<marker>just text</marker>", "must hold fields"),
        ("<marker><x>1</x>", "not well-formed XML"),
        ("", "not well-formed XML"),
        ("(1 2 3)", "not well-formed XML"),
        ('<m xmlns:a="urn:a"><a:x>1</a:x></m>', "bad element name"),
        ("<m><x.y>1</x.y></m>", "bad element name"),
    ],
)
def test_parse_marker_refuses(text: str, message: str) -> None:
    with pytest.raises(ValueFormatError, match="expected a marker like") as info:
        parse_marker(text)
    assert message in info.value.message


HOSTILE_XML = {
    "billion laughs": (
        '<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
        '<!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">'
        '<!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">]>'
        "<marker><x>&lol3;</x></marker>"
    ),
    "quadratic blowup": '<!DOCTYPE m [<!ENTITY a "' + "x" * 5000 + '">]><m><x>' + "&a;" * 200 + "</x></m>",
    "external entity": '<!DOCTYPE m [<!ENTITY xxe SYSTEM "file:///etc/passwd">]><m><x>&xxe;</x></m>',
    "external dtd": '<!DOCTYPE m SYSTEM "http://127.0.0.1:9/evil.dtd"><m><x>1</x></m>',
    "parameter entity": '<!DOCTYPE m [<!ENTITY % p SYSTEM "file:///etc/passwd"> %p;]><m/>',
    "plain dtd": "<!DOCTYPE marker><marker/>",
    "undeclared entity": "<m><x>&nope;</x></m>",
}


@pytest.mark.parametrize("name", sorted(HOSTILE_XML))
def test_hostile_xml_refused(name: str) -> None:
    with pytest.raises(ValueFormatError, match="expected a marker like"):
        parse_marker(HOSTILE_XML[name])


def test_marker_depth_limit() -> None:
    deep = "<a>" * (MAX_LIST_DEPTH + 5) + "1" + "</a>" * (MAX_LIST_DEPTH + 5)
    with pytest.raises(ValueFormatError, match="nest deeper"):
        parse_marker(deep)


def test_format_marker_refuses_what_xml_cannot_carry() -> None:
    with pytest.raises(ValueFormatError, match="XML cannot carry"):
        format_marker(Marker("m", {"x": "bell\x07"}))
    with pytest.raises(ValueFormatError, match="bad marker element name"):
        format_marker(Marker("m", {"1x": "1"}))
    with pytest.raises(ValueFormatError, match="bad marker element name"):
        format_marker(Marker("has space", {}))


# --- arbitrary input never escapes as anything but ValueFormatError --------

value_alphabet = st.text(st.sampled_from(list("() \t\n0123456789.eE+-,xnaif<>/&;!?=\"'[]%m")), max_size=60)


@pytest.mark.parametrize("parser", PARSERS)
@given(text=st.one_of(st.text(max_size=80), value_alphabet))
def test_arbitrary_text_only_raises_value_format_error(parser: Any, text: str) -> None:
    try:
        parser(text)
    except ValueFormatError as e:
        assert e.message.startswith("expected ")


# --- type-driven conversion ------------------------------------------------


@pytest.mark.parametrize(
    ("tp", "text", "expected"),
    [
        (float, "0.5", 0.5),
        (int, "3", 3),
        (bool, "on", True),
        (str, " as is ", " as is "),
        (Any, "(1 2)", "(1 2)"),
        (list[str], "(a b.c)", ["a", "b.c"]),
        (list[float], "(1 2.5)", [1.0, 2.5]),
        (list[int], "(1 2)", [1, 2]),
        (list, "(a (b))", ["a", ["b"]]),
        (list[Any], "(a (b))", ["a", ["b"]]),
        (Optional[float], "", None),  # noqa: UP045 - the typing spelling is what users write too
        (float | None, "2", 2.0),
        (str | None, "", None),
        (str | None, " ", " "),
        (Annotated[int, "doc"], "5", 5),
        (Annotated[float | None, {"unhashable": []}], " ", None),
    ],
)
def test_parse_as(tp: Any, text: str, expected: Any) -> None:
    assert parse_as(tp, text) == expected


def test_parse_as_arrays_and_markers() -> None:
    assert parse_as(Vector, "(1 2)").tolist() == [1.0, 2.0]
    assert parse_as(np.ndarray, "(1 2)").tolist() == [1.0, 2.0]
    assert [v.tolist() for v in parse_as(list[Vector], "((1) (2))")] == [[1.0], [2.0]]
    assert [v.tolist() for v in parse_as(list[np.ndarray], "((1) (2))")] == [[1.0], [2.0]]
    assert parse_as(Marker, MARKER) == parse_marker(MARKER)
    assert parse_as(Optional[Marker], "") is None  # noqa: UP045


def test_parse_as_errors() -> None:
    with pytest.raises(ValueFormatError):
        parse_as(float, "x")
    with pytest.raises(ValueFormatError):
        parse_as(list[int], "(1 x)")
    for tp in (dict[str, int], complex, int | str, "float", list[Marker]):
        with pytest.raises(TypeError):
            parse_as(tp, "1")
    assert parser_for(float) is parser_for(float)


@pytest.mark.parametrize(
    ("tp", "name"),
    [
        (float, "number"),
        (int, "integer"),
        (bool, "boolean"),
        (str, "text"),
        (Any, "text"),
        (Vector, "vector"),
        (np.ndarray, "vector"),
        (list[Vector], "vectors"),
        (list[str], "names"),
        (Marker, "marker"),
        (list[float], "list"),
        (list, "list"),
        (Optional[Vector], "vector"),  # noqa: UP045
        (Annotated[list[str] | None, "x"], "names"),
    ],
)
def test_type_name(tp: Any, name: str) -> None:
    assert type_name(tp) == name


@pytest.mark.parametrize(
    ("obj", "text"),
    [
        (None, ""),
        (True, "true"),
        (np.bool_(False), "false"),
        (3, "3"),
        (2.0, "2"),
        (np.float64(0.25), "0.25"),
        (np.int32(-4), "-4"),
        ("text", "text"),
        (np.array([1.0, 2.5]), "(1 2.5)"),
        (np.array([[1.0, 0.0], [2.0, 0.1]]), "((1 0) (2 0.1))"),
        (np.array(1.5), "1.5"),
        ([np.zeros(2), np.ones(1)], "((0 0) (1))"),
        (["a", 1, [2.5]], "(a 1 (2.5))"),
        ((), "()"),
        (Marker("m", {"x": "1"}), "<m><x>1</x></m>"),
    ],
)
def test_format_value(obj: Any, text: str) -> None:
    assert format_value(obj) == text


def test_format_value_unknown_type() -> None:
    with pytest.raises(TypeError):
        format_value({"a": 1})


# --- vector sub-properties -------------------------------------------------


@pytest.mark.parametrize(
    ("name", "index"),
    [("x", 0), ("y", 1), ("z", 2), ("roll", 3), ("pitch", 4), ("yaw", 5), ("0", 0), ("5", 5)],
)
def test_vector_index(name: str, index: int) -> None:
    assert vector_index(name, 6) == index


@pytest.mark.parametrize(
    ("name", "length"), [("z", 2), ("yaw", 3), ("6", 6), ("-1", 6), ("01", 6), ("w", 6), ("", 6)]
)
def test_vector_index_not_found(name: str, length: int) -> None:
    with pytest.raises(NotFound):
        vector_index(name, length)
