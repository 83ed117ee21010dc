"""``psctl top`` against a real gateway process: on a pseudo-terminal, whose screen a terminal
emulator (pyte) rebuilds from what psctl wrote, until q or Ctrl-C gives the terminal back; and piped,
as plain tables."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import signal
import struct
import subprocess
import termios
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from support.gateway_process import GatewayProcess, start_gateway
from support.ports import free_port
from support.psctl import PSCTL, ctrl_c_reaches_children

pyte = pytest.importorskip(
    "pyte", reason="the terminal emulator of the test extra (pip install -e '.[test]')"
)

SENSOR = """
[[services]]
name = "thermo1"
type = "sim-sensor"
"""

#: The end of a row of the table: AGE and CHANGES, right-aligned.
_AGE_AND_CHANGES = re.compile(r"^(?P<rest>.*?)\s+(?P<age>\d+(\.\d)?[smhd](\d\d[smh])?)\s+(?P<changes>\d+)$")


def parse_row(line: str) -> dict[str, str] | None:
    """NAME, VALUE, UNIT, AGE and CHANGES of a table row (columns stand two spaces or more apart;
    a unit such as "m, rad" holds one); None for a line that is not a row."""
    end = _AGE_AND_CHANGES.match(line.rstrip())
    if end is None:
        return None
    cells = re.split(r"\s{2,}", end["rest"].strip())
    if len(cells) < 2:
        return None
    return {
        "name": cells[0],
        "value": cells[1],
        "unit": cells[2] if len(cells) > 2 else "",
        "age": end["age"],
        "changes": end["changes"],
    }


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    """A gateway with a sensor ``thermo1`` whose ``data`` changes by itself (5 Hz)."""
    gw = start_gateway(tmp_path_factory.mktemp("top"), SENSOR)
    yield gw
    gw.stop()


class Terminal:
    """psctl on a pseudo-terminal of ``rows`` x ``cols``; what it writes is played into a pyte screen."""

    def __init__(self, args: list[str], rows: int, cols: int, term: str = "xterm-256color") -> None:
        self.master, self.slave = pty.openpty()
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
        self.modes_before = termios.tcgetattr(self.slave)
        self.screen = pyte.Screen(cols, rows)
        self._stream = pyte.ByteStream(self.screen)
        self._lock = threading.Lock()
        with ctrl_c_reaches_children():
            self.proc = subprocess.Popen(
                [*PSCTL, *args],
                stdin=self.slave,
                stdout=self.slave,
                stderr=self.slave,
                # curses takes COLUMNS and LINES over the terminal's own size, and a test runner
                # may export them (pytest-xdist's workers do): this terminal's size is the pty's.
                env={
                    **{k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")},
                    "TERM": term,
                    "LANG": "C.UTF-8",
                    "LC_ALL": "C.UTF-8",
                },
                start_new_session=True,
            )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                data = os.read(self.master, 65536)
            except OSError:
                return
            if not data:
                return
            with self._lock:
                self._stream.feed(data)

    def lines(self) -> list[str]:
        with self._lock:
            return [line.rstrip() for line in self.screen.display]

    def wait_for(self, what: str, found: Callable[[list[str]], bool], timeout: float = 30.0) -> list[str]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            lines = self.lines()
            if found(lines):
                return lines
            if self.proc.poll() is not None:
                # Ended: what it wrote last may still be on its way through the reader thread.
                deadline = min(deadline, time.monotonic() + 2.0)
            time.sleep(0.05)
        raise AssertionError(
            f"{what}: not on the screen (exit {self.proc.poll()}):\n" + "\n".join(self.lines())
        )

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def terminal() -> Iterator[Callable[..., Terminal]]:
    opened: list[Terminal] = []

    def open_terminal(*args: str, rows: int = 24, cols: int = 80, term: str = "xterm-256color") -> Terminal:
        opened.append(Terminal(list(args), rows, cols, term))
        return opened[-1]

    yield open_terminal
    for t in opened:
        t.close()


def rows_of(lines: list[str]) -> dict[str, dict[str, str]]:
    return {row["name"]: row for row in map(parse_row, lines) if row is not None}


def changes_of_data(lines: list[str]) -> int:
    row = rows_of(lines).get("data")
    return int(row["changes"]) if row is not None else -1


def assert_terminal_given_back(t: Terminal) -> None:
    modes = termios.tcgetattr(t.slave)
    lflag = 3
    assert modes[lflag] & (termios.ECHO | termios.ICANON) == t.modes_before[lflag] & (
        termios.ECHO | termios.ICANON
    )
    assert modes[lflag] & termios.ECHO and modes[lflag] & termios.ICANON


def test_top_on_a_terminal_updates_the_table_in_place_and_q_gives_the_terminal_back(
    gateway: GatewayProcess, terminal: Callable[..., Terminal]
) -> None:
    t = terminal("-t", gateway.address, "top", "thermo1")
    lines = t.wait_for("the table with data changed once", lambda ls: changes_of_data(ls) >= 1)
    assert "thermo1" in lines[0] and "q quits" in lines[0]
    header = next(line for line in lines if line.startswith("NAME"))
    assert header.split() == ["NAME", "VALUE", "UNIT", "AGE", "CHANGES"]
    rows = rows_of(lines)
    assert set(rows) == {"data", "location", "rate_hz"}
    assert rows["data"]["unit"] == "degC"
    assert float(rows["data"]["value"]) == pytest.approx(20, abs=50)
    # In place: the count grows on the same line, the screen does not scroll.
    seen = changes_of_data(lines)
    lines = t.wait_for("data changed again", lambda ls: changes_of_data(ls) > seen + 2)
    assert sum(1 for line in lines if line.startswith("data ")) == 1
    assert lines.index(header) == next(i for i, line in enumerate(t.lines()) if line.startswith("NAME"))

    os.write(t.master, b"q")
    assert t.proc.wait(20) == 0
    assert_terminal_given_back(t)


def test_top_shortens_values_to_the_width_of_the_terminal(
    gateway: GatewayProcess, terminal: Callable[..., Terminal]
) -> None:
    t = terminal("-t", gateway.address, "top", "thermo1", "--properties", "data,location", cols=42)
    lines = t.wait_for("the location row", lambda ls: "location" in rows_of(ls))
    rows = rows_of(lines)
    assert set(rows) == {"data", "location"}
    assert rows["location"]["value"].endswith("...")  # "(0 0 0 0 0 0)" does not fit beside the other columns
    assert rows["location"]["value"] != "(0 0 0 0 0 0)"
    os.write(t.master, b"Q")
    assert t.proc.wait(20) == 0


def test_ctrl_c_ends_top_and_gives_the_terminal_back(
    gateway: GatewayProcess, terminal: Callable[..., Terminal]
) -> None:
    t = terminal("-t", gateway.address, "top", "thermo1")
    t.wait_for("the table", lambda ls: "data" in rows_of(ls))
    # What the terminal does on Ctrl-C in cbreak mode (ISIG stays on): SIGINT to the program.
    t.proc.send_signal(signal.SIGINT)
    assert t.proc.wait(20) == 0
    assert_terminal_given_back(t)
    assert "Traceback" not in "\n".join(t.lines())


def test_a_terminal_curses_cannot_drive_is_a_clear_error(
    gateway: GatewayProcess, terminal: Callable[..., Terminal]
) -> None:
    t = terminal("-t", gateway.address, "top", "thermo1", term="no-such-terminal")
    assert t.proc.wait(20) == 2
    shown = " ".join(
        line.strip() for line in t.wait_for("the error", lambda ls: "error:" in "".join(ls)) if line
    )
    assert shown.startswith("error: cannot drive this terminal (")
    assert "pipe the output for plain tables" in shown
    assert_terminal_given_back(t)


def test_top_piped_prints_a_plain_table_on_each_change(gateway: GatewayProcess) -> None:
    done = subprocess.run(
        [*PSCTL, "-t", gateway.address, "top", "thermo1", "--count", "3", "--interval", "0.2"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    tables = [block.splitlines() for block in done.stdout.strip("\n").split("\n\n")]
    assert len(tables) == 3
    for table in tables:
        assert re.match(
            rf"^-- \d\d:\d\d:\d\d {re.escape(gateway.address)}  thermo1 \(3 properties\)$", table[0]
        )
        assert table[1].split() == ["NAME", "VALUE", "UNIT", "AGE", "CHANGES"]
        assert set(rows_of(table[2:])) == {"data", "location", "rate_hz"}
    assert int(rows_of(tables[0])["data"]["changes"]) == 0  # the current values first
    assert int(rows_of(tables[-1])["data"]["changes"]) >= 2  # then a table per change

    one = subprocess.run(
        [*PSCTL, "-t", gateway.address, "top", "thermo1", "--properties", "rate_hz", "--count", "1"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert one.returncode == 0, one.stderr
    assert set(rows_of(one.stdout.splitlines())) == {"rate_hz"}


def test_top_of_an_unknown_property_or_as_records_is_a_clear_error(gateway: GatewayProcess) -> None:
    def top(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*PSCTL, *args], capture_output=True, text=True, timeout=60, check=False)

    done = top("-t", gateway.address, "top", "thermo1", "--properties", "nosuch", "--count", "1")
    assert done.returncode == 1
    assert done.stderr.startswith("error: NOT_FOUND: ")
    done = top("-t", gateway.address, "top", "thermo1", "--format", "jsonl")
    assert done.returncode == 2
    assert done.stderr.startswith("error: top is a view for people")


def test_top_of_two_gateways_on_a_terminal_shows_the_one_that_failed_and_says_why_afterwards(
    gateway: GatewayProcess, terminal: Callable[..., Terminal]
) -> None:
    dead = f"127.0.0.1:{free_port()}"
    t = terminal("-t", gateway.address, "-t", dead, "top", "thermo1", "--properties", "data", cols=100)
    lines = t.wait_for(
        "the live gateway's row and the other's error",
        lambda ls: (
            any(line.startswith(f"{dead}: error: UNAVAILABLE") for line in ls)
            and any(line.startswith(gateway.address) for line in ls)
        ),
    )
    header = next(line for line in lines if "NAME" in line)
    assert header.split() == ["TARGET", "NAME", "VALUE", "UNIT", "AGE", "CHANGES"]
    os.write(t.master, b"q")
    assert t.proc.wait(20) == 3  # one gateway could not be reached
    assert_terminal_given_back(t)
    t.wait_for(
        "the error on stderr", lambda ls: any(line.startswith(f"[{dead}] error: UNAVAILABLE") for line in ls)
    )
