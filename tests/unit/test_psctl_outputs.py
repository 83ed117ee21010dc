"""psctl's outputs in this process: the live table of ``top`` as lines, the ages it shows, the
lines and records of one target among several, and the ``--output`` file that rotates at its bound."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from clients.aio import Event
from clients.psctl_output import RecordFile, RecordFileError, TargetOutput, record_json
from clients.psctl_top import LiveTable, age_text

T0 = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)


def event(prop: str, value: str | bytes, at: datetime = T0, removed: bool = False) -> Event:
    return Event("bot", prop, value, 1, at, 0, False, removed)


@pytest.mark.parametrize(
    ("seconds", "shown"),
    [
        (-1, "0.0s"),
        (0.44, "0.4s"),
        (9.96, "10.0s"),
        (12.7, "12s"),
        (185, "3m05s"),
        (7620, "2h07m"),
        (273600, "3d04h"),
    ],
)
def test_an_age_reads_at_a_glance(seconds: float, shown: str) -> None:
    assert age_text(seconds) == shown


def test_the_live_table_counts_changes_after_the_current_value_and_ages_from_the_last() -> None:
    table = LiveTable()
    table.units["", "speed"] = "m/s"
    table.update(event("speed", "0.5"))
    table.update(event("location", "(0 0)"))
    table.update(event("speed", "0.7", T0 + timedelta(seconds=2)))
    table.update(event("speed", "0.9", T0 + timedelta(seconds=3)))
    now = (T0 + timedelta(seconds=4)).timestamp()
    assert table.lines(None, now) == [
        "NAME      VALUE  UNIT      AGE  CHANGES",
        "location  (0 0)           4.0s        0",
        "speed     0.9    m/s      1.0s        2",
    ]
    table.update(event("location", "", removed=True))
    assert [line.split()[0] for line in table.lines(None, now)] == ["NAME", "speed"]


def test_the_live_table_shortens_values_to_the_width_and_keeps_them_on_one_line() -> None:
    table = LiveTable()
    table.update(event("marker", "<marker>\n<location>(1 2 3)</location></marker>"))
    table.update(event("frame", b"\xff" * 48213))
    lines = table.lines(60, T0.timestamp())
    assert all(len(line) <= 60 for line in lines)
    marker = next(line for line in lines if line.startswith("marker"))
    assert "<marker>\\n<loc" in marker and "..." in marker
    assert "<48213 bytes>" in next(line for line in lines if line.startswith("frame"))


def test_the_live_table_of_several_gateways_names_the_gateway_first_in_their_order() -> None:
    table = LiveTable(["gw2:1", "gw1:1"])
    table.units["gw2:1", "speed"] = "m/s"
    table.update(event("speed", "0.5"), "gw2:1")
    table.update(event("speed", "0.7"), "gw1:1")
    table.update(event("location", "(0 0)"), "gw1:1")
    assert table.lines(None, T0.timestamp()) == [
        "TARGET  NAME      VALUE  UNIT      AGE  CHANGES",
        "gw2:1   speed     0.5    m/s      0.0s        0",
        "gw1:1   location  (0 0)           0.0s        0",
        "gw1:1   speed     0.7             0.0s        0",
    ]


def test_one_target_among_several_tags_its_lines_and_json_and_holds_them_until_released(
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = TargetOutput("gw1:50051", tagged=True, held=True)
    out.line("a = 1\nb = 2")
    out.json(["x", "y"])
    out.error("NOT_FOUND: nope")
    assert capsys.readouterr() == ("", "")
    out.release()
    printed = capsys.readouterr()
    assert printed.out.splitlines() == [
        "[gw1:50051] a = 1",
        "[gw1:50051] b = 2",
        '{"target": "gw1:50051", "result": ["x", "y"]}',
    ]
    assert printed.err == "[gw1:50051] error: NOT_FOUND: nope\n"
    alone = TargetOutput("gw1:50051")
    alone.line("a = 1")
    alone.json({"value": "1"})
    assert capsys.readouterr().out == 'a = 1\n{"value": "1"}\n'


def test_a_record_always_has_its_six_keys_and_binary_data_in_base64() -> None:
    text = record_json(
        target="gw",
        kind="value",
        service="files",
        prop="blob",
        value=b"\x00\x01",
        time=T0,
        extra={"sequence": 3},
    )
    assert json.loads(text) == {
        "target": "gw",
        "service": "files",
        "property": "blob",
        "value": None,
        "time": "2026-01-02T03:04:05+00:00",
        "kind": "value",
        "data": "AAE=",
        "sequence": 3,
    }


def test_the_output_file_appends_and_moves_aside_at_its_bound(tmp_path: Path) -> None:
    path = tmp_path / "out.jsonl"
    path.write_text('{"earlier": true}\n')
    records = RecordFile(str(path), max_bytes=100, keep=2)
    try:
        for i in range(12):
            records.write(json.dumps({"n": i, "pad": "x" * 20}))
    finally:
        records.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.jsonl", "out.jsonl.1", "out.jsonl.2"]
    assert all(p.stat().st_size <= 100 for p in tmp_path.iterdir())
    newest = [json.loads(line)["n"] for line in path.read_text().splitlines()]
    assert newest[-1] == 11
    older = [json.loads(line)["n"] for line in (tmp_path / "out.jsonl.1").read_text().splitlines()]
    assert older[-1] + 1 == newest[0]  # nothing lost between the files kept


def test_an_unbounded_output_file_only_appends(tmp_path: Path) -> None:
    path = tmp_path / "all.jsonl"
    for _ in range(2):
        records = RecordFile(str(path), max_bytes=0, keep=1)
        for i in range(50):
            records.write(json.dumps({"n": i}))
        records.close()
    assert [p.name for p in tmp_path.iterdir()] == ["all.jsonl"]
    assert len(path.read_text().splitlines()) == 100


def test_a_record_the_disk_refuses_is_a_clear_error() -> None:
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    records = RecordFile("/dev/full", max_bytes=1024, keep=1)  # a device: written, never moved aside
    try:
        with pytest.raises(RecordFileError, match=r"^--output /dev/full: No space left on device$"):
            records.write('{"n": 1}')
    finally:
        records.close()
