"""Run every clause against one device and collect the outcomes.

The greeting is taken first (docs/device-spec.md §4.2): on TCP it must be the device's first
line; on a serial line the kit sends ``HELLO`` until a greeting comes, as the gateway does for a
board that resets when its port opens (§4.5). Without a greeting there is no device to check,
and every other clause is skipped.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import urlsplit

from gateway.conformance.clauses import CLAUSES, Device, Failed, Skipped
from gateway.conformance.probe import Probe, open_url
from services.kernel.line_protocol import BadLine, Hello

#: Seconds between two HELLOs on a serial line while no greeting has come: a bootloader that
#: ate the first one has handed over by then on the common boards (Optiboot waits about 1 s).
HELLO_AGAIN_S = 1.0

PASS, FAIL, SKIP = "pass", "fail", "skip"


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one clause's check found: ``status`` is pass, fail or skip."""

    number: str
    title: str
    status: str
    #: What the device should have done (fail), or why nothing was checked (skip).
    detail: str = ""
    #: The lines of the check (``> `` sent, ``< `` received); kept for a failure.
    lines: tuple[str, ...] = ()


@dataclass
class Report:
    """Every outcome of one run, and the device's greeting line."""

    url: str
    greeting: str = ""
    outcomes: tuple[Outcome, ...] = ()

    def count(self, status: str) -> int:
        """How many clauses ended with ``status``."""
        return sum(1 for o in self.outcomes if o.status == status)


def _is_greeting(frame: object) -> bool:
    return type(frame) is Hello or (isinstance(frame, BadLine) and frame.greeting)


async def _greeting(probe: Probe, serial: bool, wait: float) -> tuple[Outcome, Outcome, Hello | None]:
    """The outcomes of §4.2 (a greeting came) and §4.1 (it is well formed), and the greeting."""
    loop = asyncio.get_running_loop()
    until = loop.time() + wait
    how = "answers HELLO after the port opens" if serial else "greets first on TCP"
    first = None
    while first is None and loop.time() < until:
        if serial:
            await probe.send(b"HELLO")
        asked = loop.time()
        # Lines before the greeting (a boot banner, bytes a reset spoiled) are passed over on a
        # serial line; on TCP the greeting must be the first line.
        while (
            first is None
            and (left := min(until, asked + HELLO_AGAIN_S) - loop.time() if serial else until - loop.time())
            > 0
        ):
            heard = await probe.line(left)
            if heard is None:
                break
            if _is_greeting(heard.frame) or not serial:
                first = heard
    if first is None and not serial:  # late or silent: ask, so that the other clauses can run
        await probe.send(b"HELLO")
        first = await probe.line()
    lines = tuple(probe.transcript)
    frame = first.frame if first is not None else None
    if first is not None and _is_greeting(frame) and (serial or lines[0].startswith("< ")):
        arrived = Outcome("4.2", how, PASS)
    else:
        expected = "a greeting `HELLO 1 ...` as the first line" if not serial else "a greeting"
        arrived = Outcome("4.2", how, FAIL, f"{expected} within {wait:g} s", lines)
    title = "the greeting is `HELLO 1` with well-formed fields"
    if type(frame) is Hello:
        if frame.version != 1:
            return arrived, Outcome("4.1", title, FAIL, f"wire version 1, not {frame.version}", lines), None
        return arrived, Outcome("4.1", title, PASS), frame
    if isinstance(frame, BadLine) and frame.greeting:
        return arrived, Outcome("4.1", title, FAIL, frame.message, lines), None
    return arrived, Outcome("4.1", title, SKIP, "no greeting"), None


async def check_device(
    url: str,
    *,
    reply_wait: float = 2.0,
    greeting_wait: float = 5.0,
    writes: bool = True,
    on_outcome: Callable[[Outcome], None] | None = None,
) -> Report:
    """Check the device at ``url`` clause by clause, giving it ``reply_wait`` seconds for each reply.

    OSError or ValueError when it cannot be opened.
    """
    reader, writer = await open_url(url)
    serial = urlsplit(url).scheme == "serial"
    probe = Probe(reader, writer, reply_wait, serial=serial)
    report = Report(url)
    outcomes: list[Outcome] = []

    def record(outcome: Outcome) -> None:
        outcomes.append(outcome)
        if on_outcome is not None:
            on_outcome(outcome)

    try:
        arrived, formed, greeting = await _greeting(probe, serial, greeting_wait)
        record(arrived)
        record(formed)
        if greeting is None:
            for item in CLAUSES:
                record(Outcome(item.number, item.title, SKIP, "no usable greeting"))
            return report
        report.greeting = greeting_line(probe)
        probe.greeting = greeting
        await probe.settle()  # a board that reset on open may have greeted twice
        device = Device(greeting, writes=writes)
        for item in CLAUSES:
            start = len(probe.transcript)
            try:
                await item.check(probe, device)
            except Failed as failed:
                record(Outcome(item.number, item.title, FAIL, failed.what, tuple(probe.transcript[start:])))
                await probe.settle()
            except Skipped as skipped:
                record(Outcome(item.number, item.title, SKIP, skipped.why))
            else:
                record(Outcome(item.number, item.title, PASS))
    finally:
        report.outcomes = tuple(outcomes)
        await probe.close()
    return report


def greeting_line(probe: Probe) -> str:
    """The device's greeting as it came (the first greeting line of the transcript)."""
    for line in probe.transcript:
        if line.startswith("< ") and "HELLO" in line:
            return line[2:]
    return ""
