"""The storage service's file names and its directory-bound file operations, on a real directory."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.engine.sizes import MAX_ANSWER_BYTES, MAX_MESSAGE_BYTES
from services.apps.storage import MAX_FILE_SIZE, check_name
from services.apps.storage.disk import FileInfo, Folder
from services.apps.storage.find import FindQuery, format_time, glob_matcher, parse_time
from services.apps.storage.names import MAX_SEGMENT_BYTES, TEMP_PREFIX, is_carried
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    ResourceExhausted,
    Unavailable,
)


@pytest.mark.parametrize(
    "name", ["a.txt", "charts/door.scxml", "x/y/z/deep.json", "ünïcode-名前.md", ".hidden", "a..b", "1"]
)
def test_names_the_service_carries(name: str) -> None:
    assert check_name(name) == name


@pytest.mark.parametrize(
    ("name", "why"),
    [
        ("", "empty"),
        ("../x", "segment '..'"),
        ("a/../../x", "segment '..'"),
        ("./a", "segment '.'"),
        ("/etc/passwd", "absolute path"),
        ("a//b", "empty segment"),
        ("a/", "empty segment"),
        ("a b", "whitespace"),
        ("a\nb", "whitespace"),
        ("a(1)", "'('"),
        ("a\\b", "'\\\\'"),
        ("a\x00b", "control character"),
        ("x" * (MAX_SEGMENT_BYTES + 1), "the filesystem holds at most 255"),
        ("é" * 128, "a segment of 256 bytes"),
        ("/".join(["d"] * 17), "17 segments deep"),
        (f"{TEMP_PREFIX}abc", "temporary files"),
        ("\ud800", "UTF-8 cannot encode"),
    ],
)
def test_names_refused_say_why(name: str, why: str) -> None:
    with pytest.raises(InvalidArgument) as refused:
        check_name(name)
    assert why in refused.value.message


@given(st.text(min_size=1, max_size=60))
def test_an_accepted_name_stays_below_the_directory(name: str) -> None:
    if not is_carried(name):
        return
    base = Path("/srv/store")
    joined = Path(os.path.normpath(base / name))
    assert joined.is_relative_to(base) and joined != base, name


_NAME_CHARS = st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00")


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    name=st.text(_NAME_CHARS, min_size=1, max_size=40),
    text=st.text(st.characters(blacklist_categories=("Cs",))),
)
def test_any_carried_name_and_text_round_trip_inside_the_directory(
    tmp_path: Path, name: str, text: str
) -> None:
    if not is_carried(name):
        with pytest.raises(InvalidArgument):
            check_name(name)
        return
    root = tmp_path / "root"
    root.mkdir(exist_ok=True)
    folder = Folder(root)
    try:
        folder.write(name, text.encode("utf-8"))
    except FailedPrecondition:
        return  # the name runs through a file an earlier example stored (a/b after a)
    assert folder.read(name, 1 << 20).decode("utf-8") == text
    assert (root / name).resolve().is_relative_to(root.resolve())
    assert not any(p.name.startswith(TEMP_PREFIX) for p in root.rglob("*"))


def test_the_largest_file_fits_one_message_with_room_for_its_envelope() -> None:
    assert MAX_FILE_SIZE + 32 * 1024 <= MAX_ANSWER_BYTES < MAX_MESSAGE_BYTES


def test_store_read_remove_round_trip(tmp_path: Path) -> None:
    folder = Folder(tmp_path)
    folder.write("charts/door.scxml", b"<scxml/>")
    assert folder.read("charts/door.scxml", 100) == b"<scxml/>"
    folder.write("charts/door.scxml", b"<scxml version='1.0'/>")
    assert (tmp_path / "charts" / "door.scxml").read_bytes() == b"<scxml version='1.0'/>"
    info = folder.info("charts/door.scxml")
    assert (info.name, info.size) == ("charts/door.scxml", 22)
    assert [f.name for f in folder.scan(lambda _: True, 10)[0]] == ["charts/door.scxml"]
    folder.remove("charts/door.scxml")
    assert not (tmp_path / "charts" / "door.scxml").exists()
    with pytest.raises(NotFound):
        folder.read("charts/door.scxml", 100)
    with pytest.raises(NotFound):
        folder.remove("charts/door.scxml")


def test_a_store_leaves_no_temporary_file_and_keeps_the_mode(tmp_path: Path) -> None:
    folder = Folder(tmp_path)
    (tmp_path / "run.sh").write_text("old")
    (tmp_path / "run.sh").chmod(0o750)
    folder.write("run.sh", b"new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.sh"]
    assert stat.S_IMODE((tmp_path / "run.sh").stat().st_mode) == 0o750


def test_symbolic_links_are_never_followed(tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("secret")
    store = tmp_path / "store"
    store.mkdir()
    (store / "out").symlink_to(outside)
    (store / "passwd").symlink_to("/etc/passwd")
    folder = Folder(store)
    for name in ("out/secret.txt", "passwd"):
        with pytest.raises(FailedPrecondition, match="symbolic link"):
            folder.read(name, 1000)
        with pytest.raises(FailedPrecondition, match="symbolic link"):
            folder.write(name, b"overwritten")
        with pytest.raises(FailedPrecondition, match="symbolic link"):
            folder.info(name)
    with pytest.raises(FailedPrecondition, match="symbolic link"):
        folder.write("out/new.txt", b"planted")
    assert sorted(p.name for p in outside.iterdir()) == ["secret.txt"]
    assert (outside / "secret.txt").read_text() == "secret"
    assert (store / "passwd").is_symlink()
    assert folder.scan(lambda _: True, 10) == ([], False)


def test_a_directory_gone_is_unavailable(tmp_path: Path) -> None:
    folder = Folder(tmp_path / "gone")
    with pytest.raises(Unavailable, match="cannot be opened"):
        folder.read("a.txt", 10)
    with pytest.raises(Unavailable, match="cannot be opened"):
        folder.write("a.txt", b"x")


def test_a_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "pipe")
    with pytest.raises(FailedPrecondition, match="not a regular file"):
        Folder(tmp_path).read("pipe", 100)


def test_a_file_over_the_limit_is_refused(tmp_path: Path) -> None:
    (tmp_path / "big.txt").write_bytes(b"x" * 101)
    with pytest.raises(ResourceExhausted, match="101 bytes, over the limit of 100"):
        Folder(tmp_path).read("big.txt", 100)
    assert Folder(tmp_path).read("big.txt", 101) == b"x" * 101


def test_scan_skips_what_it_cannot_carry_and_stops_at_its_limit(tmp_path: Path) -> None:
    for name in ("b.txt", "a.txt", "sub/c.txt", "with space.txt", f"{TEMP_PREFIX}1234"):
        path = tmp_path / name
        path.parent.mkdir(exist_ok=True)
        path.write_text(name)
    (tmp_path / "link.txt").symlink_to(tmp_path / "a.txt")
    folder = Folder(tmp_path)
    found, truncated = folder.scan(lambda _: True, 10)
    assert [f.name for f in found] == ["a.txt", "b.txt", "sub/c.txt"] and not truncated
    found, truncated = folder.scan(lambda _: True, 2)
    assert len(found) == 2 and truncated
    found, _ = folder.scan(lambda f: f.name.startswith("sub/"), 10)
    assert [f.name for f in found] == ["sub/c.txt"]


def test_find_conditions() -> None:
    old = FileInfo("logs/a.txt", 10, parse_time("2026-01-01T00:00:00Z", "t") or 0)
    new = FileInfo("img/b.png", 5000, parse_time("2026-06-01T00:00:00Z", "t") or 0)
    assert glob_matcher("*.png")("img/b.png") and not glob_matcher("*.png")("img/b.png.txt")
    query = FindQuery.parse(pattern="", min_size="100", max_size="", newer="2026-03-01", older="")
    assert [f.name for f in (old, new) if query.matches(f)] == ["img/b.png"]
    query = FindQuery.parse(pattern="logs/*", min_size="", max_size="10", newer="", older="2026-02-01T00:00Z")
    assert [f.name for f in (old, new) if query.matches(f)] == ["logs/a.txt"]
    with pytest.raises(InvalidArgument, match="min_size"):
        FindQuery.parse(pattern="", min_size="-1", max_size="", newer="", older="")
    with pytest.raises(InvalidArgument, match="ISO 8601"):
        FindQuery.parse(pattern="", min_size="", max_size="", newer="yesterday", older="")
    assert format_time(old.mtime_ns) == "2026-01-01T00:00:00.000000Z"
