"""``psctl top SERVICE``: a service's properties as a table that changes in place as they do.

One Listen of the properties on each gateway feeds a :class:`LiveTable` (name, value, unit, age
since the last change, changes seen; the gateway first, with several); on a terminal curses draws
it over the whole screen, at most ten times a second and once a second for the ages, until q or
Ctrl-C, and gives the terminal back as it found it. Piped (no terminal on stdin and stdout) it
prints a plain table whenever values changed, at most once per ``interval``: the first as soon as
the current values are in.
"""

from __future__ import annotations

import asyncio
import contextlib
import locale
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

from clients.aio import AsyncClient, Event, Mark, Selector
from clients.errors import PropertyServiceError
from clients.values import Value

if TYPE_CHECKING:
    import curses  # imported when drawn: the standard library has no curses on Windows, and piped needs none

__all__ = ["MAX_ROWS", "LiveTable", "StreamEnded", "TopError", "TopSource", "age_text", "run_top"]

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
    """The latest value of each property of each target, when it last changed and how often it
    did; drawn as lines by :meth:`lines`, with a TARGET column first when there are several
    ``targets`` (their rows in that order)."""

    def __init__(self, targets: Sequence[str] = ("",)) -> None:
        self._show_target = len(targets) > 1
        self._order = {target: i for i, target in enumerate(targets)}
        #: (target, property) → unit, from each target's model of the service.
        self.units: dict[tuple[str, str], str] = {}
        self._rows: dict[tuple[str, str], _Row] = {}
        #: Set by each change, cleared by whoever draws.
        self.changed = asyncio.Event()

    def __len__(self) -> int:
        return len(self._rows)

    def update(self, ev: Event, target: str = "") -> None:
        """One event of ``target``'s Listen: the first of a property is its current value (0 changes)."""
        key = (target, ev.property)
        if ev.removed:
            self._rows.pop(key, None)
        else:
            row = self._rows.get(key)
            when = ev.time.timestamp()
            if row is not None:
                row.value, row.changed, row.changes = _one_line(ev.value), when, row.changes + 1
            elif len(self._rows) < MAX_ROWS:
                self._rows[key] = _Row(_one_line(ev.value), when, 0)
        self.changed.set()

    def lines(self, width: int | None, now: float) -> list[str]:
        """The header and one line per property, by target (in their order) and name; values shortened to fit
        ``width`` (None: whole)."""
        keys = sorted(self._rows, key=lambda key: (self._order.get(key[0], len(self._order)), key[1]))
        columns = ["TARGET"] if self._show_target else []
        columns += ["NAME", "VALUE", "UNIT", "AGE", "CHANGES"]
        cells = [
            [
                *([target] if self._show_target else []),
                name,
                self._rows[target, name].value,
                self.units.get((target, name), ""),
                age_text(now - self._rows[target, name].changed),
                str(self._rows[target, name].changes),
            ]
            for target, name in keys
        ]
        widths = [max([len(title), *(len(row[i]) for row in cells)]) for i, title in enumerate(columns)]
        # Room for an age of "10.0s" and a count in the millions from the start: columns that do
        # not move while the numbers grow.
        widths[-2], widths[-1] = max(widths[-2], _AGE_WIDTH), max(widths[-1], _CHANGES_WIDTH)
        value = columns.index("VALUE")
        if width is not None:
            for i in range(value):  # TARGET and NAME: half the width at most, together
                widths[i] = min(widths[i], max(width // (2 * value), 4))
            fixed = sum(widths) - widths[value] + 2 * (len(columns) - 1)
            widths[value] = max(width - fixed, 5)
        right = {len(columns) - 2, len(columns) - 1}  # AGE and CHANGES: numbers, right-aligned

        def line(row: list[str]) -> str:
            return "  ".join(
                f"{cell:>{w}}" if i in right else f"{_shortened(cell, w):<{w}}"
                for i, (cell, w) in enumerate(zip(row, widths, strict=True))
            ).rstrip()

        return [line(columns), *(line(row) for row in cells)]


async def _units(client: AsyncClient, service: str) -> tuple[dict[str, str], list[str]]:
    """The unit of each property of ``service``, and the names of those a Listen can follow."""
    model = await client.describe(service)
    units = {p.name: p.unit for p in model.properties if p.unit}
    listenable = [p.name for p in model.properties if p.access.listenable]
    return units, listenable


@dataclass
class TopSource:
    """One gateway whose properties ``top`` shows: its ``-t`` and a client of it."""

    target: str
    client: AsyncClient


class _Follow:
    """Feeds the table from one target's Listen; what ended it, when it failed, is ``error``."""

    def __init__(self, source: TopSource, table: LiveTable, started: Callable[[], None]) -> None:
        self.source = source
        self._table = table
        self._started = started
        self.error: Exception | None = None

    async def run(self, service: str, paths: list[str] | None) -> None:
        try:
            await self._listen(service, paths)
        except (PropertyServiceError, TopError) as e:
            self.error = e
            self._table.changed.set()  # drawn: the failure's line
        finally:
            self._started()  # a target that failed before its current values came holds nothing up

    async def _listen(self, service: str, paths: list[str] | None) -> None:
        target, client = self.source.target, self.source.client
        units, listenable = await _units(client, service)
        self._table.units.update({(target, name): unit for name, unit in units.items()})
        chosen = paths if paths else listenable
        if not chosen:
            raise TopError(f"{service} has no property a Listen can follow; name some with --properties")
        selectors: list[Selector] = [(service, path) for path in chosen]
        stream = client.listen(*selectors[0], *selectors[1:], marks=True)
        try:
            async for item in stream:
                if isinstance(item, Mark):
                    if item is Mark.SYNC:
                        self._started()
                        self._table.changed.set()
                    continue
                self._table.update(item, target)
        finally:
            await stream.aclose()
        raise StreamEnded("the gateway ended the stream")


async def _until_done(
    follows: list[asyncio.Task[None]], show: Callable[[], AsyncIterator[None]], duration: float | None
) -> None:
    """Run ``show`` while any of ``follows`` runs; ``show`` ending, every follow ending, or
    ``duration`` ends them all."""
    shower = asyncio.ensure_future(_drain(show()))
    feeding: asyncio.Future[list[None]] = asyncio.gather(*follows)
    both: list[asyncio.Future[Any]] = [feeding, shower]
    try:
        async with asyncio.timeout(duration):
            await asyncio.wait(both, return_when=asyncio.FIRST_COMPLETED)
    except TimeoutError:
        pass
    finally:
        for task in [*both, *follows]:
            task.cancel()
        await asyncio.gather(*both, *follows, return_exceptions=True)


async def _drain(items: AsyncIterator[None]) -> None:
    async for _ in items:
        pass


async def run_top(
    sources: list[TopSource],
    service: str,
    paths: list[str] | None,
    *,
    interval: float,
    count: int | None,
    duration: float | None,
    print_line: Callable[[str], None],
    report: Callable[[str, Exception], None],
) -> None:
    """Show ``paths`` of ``service`` (every listenable property when None) of every source until
    q, Ctrl-C, ``duration``, every source failing, or, piped, ``count`` tables. ``print_line``
    prints a piped table's lines; ``report(target, error)`` tells of a source that failed (the others
    go on): at once when piped, once the terminal is given back when drawn."""
    table = LiveTable([source.target for source in sources])
    started = asyncio.Event()
    waiting = len(sources)

    def one_started() -> None:
        nonlocal waiting
        waiting -= 1
        if waiting <= 0:
            started.set()

    follows = [_Follow(source, table, _once(one_started)) for source in sources]
    heading = sources[0].target if len(sources) == 1 else f"{len(sources)} gateways"
    heading = f"{heading}  {service}"
    interactive = sys.stdin.isatty() and sys.stdout.isatty()

    async def follow(one: _Follow) -> None:
        await one.run(service, paths)
        if one.error is not None and not interactive:
            report(one.source.target, one.error)

    if interactive:
        try:
            with _terminal() as screen:  # first: a terminal curses cannot drive asks no gateway
                tasks = [asyncio.create_task(follow(one)) for one in follows]
                await _until_done(tasks, lambda: _draw(screen, table, heading, follows), duration)
        finally:
            for one in follows:
                if one.error is not None:
                    report(one.source.target, one.error)
    else:
        await _until_done(
            [asyncio.create_task(follow(one)) for one in follows],
            lambda: _print_tables(
                table,
                started=started,
                alive=lambda: any(one.error is None for one in follows),
                heading=heading,
                interval=interval,
                count=count,
                print_line=print_line,
            ),
            duration,
        )


def _once(call: Callable[[], None]) -> Callable[[], None]:
    done = False

    def once() -> None:
        nonlocal done
        if not done:
            done = True
            call()

    return once


async def _print_tables(
    table: LiveTable,
    *,
    started: asyncio.Event,
    alive: Callable[[], bool],
    heading: str,
    interval: float,
    count: int | None,
    print_line: Callable[[str], None],
) -> AsyncIterator[None]:
    """Piped: a table when values changed, the first once the current values are in (of every
    target that did not fail); at most one per ``interval``; ``count`` of them at most."""
    await started.wait()
    printed = 0
    while count is None or printed < count:
        await table.changed.wait()
        table.changed.clear()
        if not alive():
            return  # every target failed: their errors say so, an empty table would not
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


async def _draw(
    screen: curses.window, table: LiveTable, heading: str, follows: list[_Follow]
) -> AsyncIterator[None]:
    """Draw ``table`` on ``screen`` when it changed (ten times a second at most) and every second
    for the ages, with a line for each target that failed; end on q."""
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
            failed = [f"{one.source.target}: error: {one.error}" for one in follows if one.error is not None]
            lines = [status[: cols - 1], *(f[: cols - 1] for f in failed), "", *table.lines(cols - 1, now)]
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
