"""``psctl top SERVICE``: a service's properties as a table that changes in place as they do.

One Listen of the properties feeds a :class:`LiveTable` (name, value, unit, age since the last
change, changes seen); on a terminal curses draws it over the whole screen, at most ten times a
second and once a second for the ages, until q or Ctrl-C, and gives the terminal back as it found
it. Piped (no terminal on stdin and stdout) it prints a plain table whenever values changed, at most
once per ``interval``: the first as soon as the current values are in.
"""

from __future__ import annotations

import asyncio
import contextlib
import locale
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

from clients.aio import AsyncClient, Event, Mark, Selector
from clients.values import Value

if TYPE_CHECKING:
    import curses  # imported when drawn: the standard library has no curses on Windows, and piped needs none

__all__ = ["MAX_ROWS", "LiveTable", "StreamEnded", "TopError", "age_text", "run_top"]

#: Redraws a second at most on a terminal: a property that changes at 1 kHz costs ten draws.
_MAX_FRAMES_PER_S = 10
#: The widths of the AGE and CHANGES columns; VALUE takes what the terminal has left.
_AGE_WIDTH = 7
_CHANGES_WIDTH = 7
#: Most properties a table holds (rows for more are not made): a pattern over a huge group stays bounded.
MAX_ROWS = 10_000


class TopError(Exception):
    """psctl top cannot run as asked (no properties to show, a terminal curses cannot drive)."""


class StreamEnded(TopError):
    """The gateway ended the Listen that fed the table, without an error status."""


def age_text(seconds: float) -> str:
    """An age as a person reads it at a glance: ``0.4s``, ``12s``, ``3m05s``, ``2h07m``, ``3d04h``."""
    seconds = max(seconds, 0.0)
    if seconds < 10:
        return f"{seconds:.1f}s"
    whole = int(seconds)
    if whole < 60:
        return f"{whole}s"
    if whole < 3600:
        return f"{whole // 60}m{whole % 60:02d}s"
    if whole < 86400:
        return f"{whole // 3600}h{whole % 3600 // 60:02d}m"
    return f"{whole // 86400}d{whole % 86400 // 3600:02d}h"


def _one_line(value: Value) -> str:
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    return value.replace("\r", "\\r").replace("\n", "\\n")


def _shortened(text: str, width: int) -> str:
    if len(text) <= width:
        return text
    return text[: max(width - 3, 0)] + "..." if width > 3 else text[:width]


@dataclass
class _Row:
    value: str
    changed: float  # seconds since the epoch: the value's own time
    changes: int


class LiveTable:
    """The latest value of each property, when it last changed and how often it did; drawn as
    lines by :meth:`lines`. ``units``: property name → unit (from the service's model)."""

    def __init__(self, units: dict[str, str]) -> None:
        self._units = units
        self._rows: dict[str, _Row] = {}
        #: Set by each change, cleared by whoever draws.
        self.changed = asyncio.Event()

    def __len__(self) -> int:
        return len(self._rows)

    def update(self, ev: Event) -> None:
        """One event of the Listen: the first of a property is its current value (0 changes)."""
        if ev.removed:
            self._rows.pop(ev.property, None)
        else:
            row = self._rows.get(ev.property)
            when = ev.time.timestamp()
            if row is not None:
                row.value, row.changed, row.changes = _one_line(ev.value), when, row.changes + 1
            elif len(self._rows) < MAX_ROWS:
                self._rows[ev.property] = _Row(_one_line(ev.value), when, 0)
        self.changed.set()

    def lines(self, width: int | None, now: float) -> list[str]:
        """The header and one line per property in name order; values shortened to fit ``width``
        (None: whole)."""
        names = sorted(self._rows)
        name_width = max([len("NAME"), *(len(n) for n in names)])
        unit_width = max([len("UNIT"), *(len(self._units.get(n, "")) for n in names)])
        if width is not None:
            name_width = min(name_width, max(width // 3, 4))
        fixed = name_width + unit_width + _AGE_WIDTH + _CHANGES_WIDTH + 8  # four two-space gaps
        value_width = (
            max(len("VALUE"), 5, *(len(r.value) for r in self._rows.values()))
            if width is None
            else max(width - fixed, 5)
        )

        def line(name: str, value: str, unit: str, age: str, changes: str) -> str:
            return (
                f"{_shortened(name, name_width):<{name_width}}  "
                f"{_shortened(value, value_width):<{value_width}}  "
                f"{unit:<{unit_width}}  {age:>{_AGE_WIDTH}}  {changes:>{_CHANGES_WIDTH}}"
            ).rstrip()

        out = [line("NAME", "VALUE", "UNIT", "AGE", "CHANGES")]
        for name in names:
            row = self._rows[name]
            out.append(
                line(
                    name, row.value, self._units.get(name, ""), age_text(now - row.changed), str(row.changes)
                )
            )
        return out


async def _units(client: AsyncClient, service: str) -> tuple[dict[str, str], list[str]]:
    """The unit of each property of ``service``, and the names of those a Listen can follow."""
    model = await client.describe(service)
    units = {p.name: p.unit for p in model.properties if p.unit}
    listenable = [p.name for p in model.properties if p.access.listenable]
    return units, listenable


async def _follow(
    client: AsyncClient, selectors: list[Selector], table: LiveTable, synced: asyncio.Event
) -> None:
    """Feed ``table`` from one Listen of ``selectors`` until cancelled (or the stream fails)."""
    stream = client.listen(*selectors[0], *selectors[1:], marks=True)
    try:
        async for item in stream:
            if isinstance(item, Mark):
                if item is Mark.SYNC:
                    synced.set()
                    table.changed.set()
                continue
            table.update(item)
    finally:
        await stream.aclose()


async def _until_done(
    follow: asyncio.Task[None], show: Callable[[], AsyncIterator[None]], duration: float | None
) -> None:
    """Run ``show`` while ``follow`` runs; the first to end (or ``duration``) ends both. A failed
    Listen raises its error here."""
    shower = asyncio.ensure_future(_drain(show()))
    both = {follow, shower}
    try:
        async with asyncio.timeout(duration):
            await asyncio.wait(both, return_when=asyncio.FIRST_COMPLETED)
    except TimeoutError:
        pass
    finally:
        for task in both:
            task.cancel()
        await asyncio.gather(*both, return_exceptions=True)
    if follow.done() and not follow.cancelled():
        follow.result()  # raises the stream's error
        raise StreamEnded("the gateway ended the stream")


async def _drain(items: AsyncIterator[None]) -> None:
    async for _ in items:
        pass


async def run_top(
    client: AsyncClient,
    service: str,
    paths: list[str] | None,
    *,
    interval: float,
    count: int | None,
    duration: float | None,
    print_line: Callable[[str], None],
    title: str,
) -> None:
    """Show ``paths`` of ``service`` (every listenable property when None) until q, Ctrl-C,
    ``duration``, or, piped, ``count`` tables. ``print_line`` prints a piped table's lines."""
    units, listenable = await _units(client, service)
    chosen = paths if paths else listenable
    if not chosen:
        raise TopError(f"{service} has no property a Listen can follow; name some with --properties")
    table = LiveTable(units)
    synced = asyncio.Event()
    follow = asyncio.create_task(_follow(client, [(service, p) for p in chosen], table, synced))
    heading = f"{title}  {service}"
    if sys.stdin.isatty() and sys.stdout.isatty():
        with _terminal() as screen:
            await _until_done(follow, lambda: _draw(screen, table, heading), duration)
    else:
        await _until_done(
            follow,
            lambda: _print_tables(
                table, synced=synced, heading=heading, interval=interval, count=count, print_line=print_line
            ),
            duration,
        )


async def _print_tables(
    table: LiveTable,
    *,
    synced: asyncio.Event,
    heading: str,
    interval: float,
    count: int | None,
    print_line: Callable[[str], None],
) -> AsyncIterator[None]:
    """Piped: a table when values changed, the first once the current values are in; at most one
    per ``interval``; ``count`` of them at most."""
    await synced.wait()
    printed = 0
    while count is None or printed < count:
        await table.changed.wait()
        table.changed.clear()
        now = time.time()
        clock = datetime.fromtimestamp(now).strftime("%H:%M:%S")
        print_line(f"-- {clock} {heading} ({len(table)} properties)")
        for line in table.lines(None, now):
            print_line(line)
        print_line("")
        printed += 1
        yield
        await asyncio.sleep(interval)


@contextlib.contextmanager
def _terminal() -> Iterator[curses.window]:
    """curses on the whole screen, keys read one at a time without echo; the terminal as it was
    afterwards, whatever ends the view (q, Ctrl-C, an error)."""
    try:
        import curses  # only a terminal view needs it
    except ImportError:
        raise TopError("this Python has no curses (Windows): pipe the output for plain tables") from None
    locale.setlocale(locale.LC_ALL, "")  # curses then writes UTF-8 values as characters
    try:
        screen = curses.initscr()
    except curses.error as e:
        raise TopError(f"cannot drive this terminal ({e}); pipe the output for plain tables") from None
    try:
        curses.noecho()
        curses.cbreak()
        screen.keypad(True)
        screen.nodelay(True)
        with contextlib.suppress(curses.error):
            curses.curs_set(0)  # a terminal without an invisible cursor shows it: no harm
        yield screen
    finally:
        screen.keypad(False)
        curses.nocbreak()
        curses.echo()
        curses.endwin()


async def _draw(screen: curses.window, table: LiveTable, heading: str) -> AsyncIterator[None]:
    """Draw ``table`` on ``screen`` when it changed (ten times a second at most) and every second
    for the ages; end on q."""
    import curses  # loaded by _terminal already

    loop = asyncio.get_running_loop()
    quit_pressed = asyncio.Event()

    def on_key() -> None:
        while (key := screen.getch()) != -1:
            if key in (ord("q"), ord("Q")):
                quit_pressed.set()
            table.changed.set()  # a resize (KEY_RESIZE) or any key: draw again

    fd = sys.stdin.fileno()
    loop.add_reader(fd, on_key)
    try:
        while not quit_pressed.is_set():
            table.changed.clear()
            rows, cols = screen.getmaxyx()
            now = time.time()
            screen.erase()
            clock = datetime.fromtimestamp(now).strftime("%H:%M:%S")
            status = f"{heading}  {len(table)} properties  {clock}  q quits"
            lines = [status[: cols - 1], "", *table.lines(cols - 1, now)]
            for y, text in enumerate(lines[:rows]):
                with contextlib.suppress(curses.error):  # the bottom-right cell cannot be written
                    screen.addnstr(y, 0, text, cols - 1)
            screen.refresh()
            yield
            await asyncio.sleep(1 / _MAX_FRAMES_PER_S)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1.0):
                    await _first(table.changed.wait(), quit_pressed.wait())
    finally:
        loop.remove_reader(fd)


async def _first(*waits: object) -> None:
    """Wait until the first of ``waits`` (coroutines) is done; cancel the rest."""
    tasks = [asyncio.ensure_future(w) for w in waits]  # type: ignore[call-overload]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
