"""Property paths, service names and Listen wildcard patterns."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.kernel.errors import Code, InvalidArgument
from services.kernel.paths import (
    MAX_PATH_LENGTH,
    compile_pattern,
    is_pattern,
    match,
    split_path,
    validate_path,
    validate_pattern,
    validate_service_name,
)

_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-"
segments = st.text(_CHARS, min_size=1, max_size=64)
paths = st.lists(segments, min_size=1, max_size=6).map(".".join).filter(lambda p: len(p) <= MAX_PATH_LENGTH)


@pytest.mark.parametrize(
    "path",
    ["location", "location.x", "robots.scout-1.location", "a_b.C9", "0", "x" * 64, ".".join(["a"] * 128)],
)
def test_valid_paths(path: str) -> None:
    assert validate_path(path) == path


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ("loc..x", 'bad property path "loc..x": empty segment at position 4'),
        (".a", "empty segment at position 0"),
        ("a.", "empty segment at position 2"),
        ("", 'bad property path "": it is empty'),
        ("a b", "character ' ' at position 1"),
        ("robots.*.location", "character '*' at position 7"),
        ("a/b", "character '/' at position 1"),
        ("ä", "character 'ä' at position 0"),
        ("a." + "x" * 65, "segment at position 2 has 65 characters, the limit is 64"),
        (".".join(["ab"] * 100), "299 characters, the limit is 256"),
    ],
)
def test_invalid_paths(path: str, message: str) -> None:
    with pytest.raises(InvalidArgument) as info:
        validate_path(path)
    assert info.value.code == Code.INVALID_ARGUMENT
    assert message in info.value.message


def test_split_path() -> None:
    assert split_path("robots.scout1.location") == ["robots", "scout1", "location"]
    assert split_path("x") == ["x"]
    with pytest.raises(InvalidArgument):
        split_path("a..b")


def test_service_names() -> None:
    assert validate_service_name("scout-7") == "scout-7"
    assert validate_service_name("registry") == "registry"
    for bad, message in [
        ("a.b", "has no dots"),
        ("", "it is empty"),
        ("x" * 65, "65 characters, the limit is 64"),
        ("my robot", "character ' ' at position 2"),
        ("*", "character '*'"),
    ]:
        with pytest.raises(InvalidArgument) as info:
            validate_service_name(bad)
        assert message in info.value.message, bad
        assert info.value.message.startswith("bad service name")


def test_patterns() -> None:
    assert validate_pattern("robots.*.location") == "robots.*.location"
    assert validate_pattern("*") == "*"
    assert validate_pattern("location") == "location"
    assert is_pattern("robots.*.location")
    assert not is_pattern("robots.scout1.location")
    with pytest.raises(InvalidArgument, match=r"\* matches a whole segment only"):
        validate_pattern("robots.scout*.location")
    with pytest.raises(InvalidArgument, match="empty segment"):
        validate_pattern("robots..*")
    with pytest.raises(InvalidArgument, match="bad property pattern"):
        compile_pattern("a**")


@pytest.mark.parametrize(
    ("pattern", "path", "expected"),
    [
        ("robots.*.location", "robots.scout1.location", True),
        ("robots.*.location", "robots.scout1.sensor.location", False),
        ("robots.*.location", "robots.location", False),
        ("robots.*", "robots.scout1", True),
        ("robots.*", "robots.scout1.location", False),
        ("*", "location", True),
        ("*", "location.x", False),
        ("*.*", "location.x", True),
        ("*.x", "location.x", True),
        ("*.x", "location.y", False),
        ("location", "location", True),
        ("location", "location.x", False),
        ("loc-1", "loc_1", False),
        ("a.*", "a.", False),
        ("a.*", "a.b c", False),
    ],
)
def test_match(pattern: str, path: str, expected: bool) -> None:
    assert match(pattern, path) is expected
    assert compile_pattern(pattern)(path) is expected


def test_compile_pattern_is_cached() -> None:
    assert compile_pattern("robots.*.location") is compile_pattern("robots.*.location")


@given(paths)
def test_every_path_matches_itself(path: str) -> None:
    assert validate_path(path) == path
    assert match(path, path)


@given(paths, st.data())
def test_star_stands_for_exactly_one_segment(path: str, data: st.DataObject) -> None:
    parts = path.split(".")
    i = data.draw(st.integers(0, len(parts) - 1))
    pattern = ".".join([*parts[:i], "*", *parts[i + 1 :]])
    assert match(pattern, path)
    # Replacing the segment by two segments (a dot inside) never matches.
    spanned = ".".join([*parts[:i], parts[i] + "." + parts[i], *parts[i + 1 :]])
    assert not match(pattern, spanned)
    # Dropping the segment never matches either.
    dropped = ".".join([*parts[:i], *parts[i + 1 :]])
    assert not match(pattern, dropped)


@given(st.text(max_size=300))
def test_arbitrary_text_is_valid_or_invalid_argument(text: str) -> None:
    for check in (validate_path, validate_service_name, validate_pattern):
        try:
            assert check(text) == text
        except InvalidArgument as e:
            assert e.message.startswith("bad ")
