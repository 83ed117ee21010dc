"""``psgateway device-check URL``: check a device against docs/device-spec.md, clause by clause.

  psgateway device-check tcp://127.0.0.1:7001
  psgateway device-check 'serial:///dev/ttyUSB0?baudrate=115200'
  psgateway device-check --read-only tcp://robot.local:7000

Each clause prints PASS, FAIL or SKIP with its number in docs/device-spec.md; a failure shows
what the device should have done and the lines of the check (> sent, < received). The kit sends
one request at a time, in pieces the device's rxbuf holds. It SETs only values a conforming
device refuses or holds already (--read-only: none).

Exit status: 0 every clause passed or was skipped, 1 a clause failed, 2 the device could not
be reached (a bad URL, a refused connection, a port that does not open).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import Any, TextIO

from gateway.conformance import FAIL, PASS, SKIP, Outcome, Report, check_device

_LABEL = {PASS: "PASS", FAIL: "FAIL", SKIP: "SKIP"}


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.05 <= value <= 600:
        raise argparse.ArgumentTypeError(f"{value:g} s is outside 0.05..600")
    return value


def add_parser(subparsers: Any) -> None:
    """Add the ``device-check`` subcommand to ``subparsers`` (from ``ArgumentParser.add_subparsers``)."""
    parser: argparse.ArgumentParser = subparsers.add_parser(
        "device-check",
        help="check a device on TCP or a serial port against the device specification",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("url", metavar="URL", help="tcp://HOST:PORT or serial:///dev/PORT?baudrate=N")
    parser.add_argument(
        "--timeout",
        type=_seconds,
        default=2.0,
        help="seconds the device has for each reply (default 2; the gateway allows 5)",
    )
    parser.add_argument(
        "--greeting-wait",
        type=_seconds,
        default=5.0,
        help="seconds to wait for the greeting; a board that resets when its port opens needs a "
        "few (default 5)",
    )
    parser.add_argument(
        "--read-only", action="store_true", help="send no SET at all (skips the clauses of §3.2)"
    )
    parser.set_defaults(func=run)


def print_outcome(outcome: Outcome, out: TextIO) -> None:
    """One clause's line, and for a failure what was expected and the lines of the check."""
    line = f"{_LABEL[outcome.status]}  §{outcome.number:<5} {outcome.title}"
    if outcome.status == SKIP:
        line += f" ({outcome.detail})"
    print(line, file=out)
    if outcome.status == FAIL:
        print(f"      expected: {outcome.detail}", file=out)
        for wire in outcome.lines:
            print(f"      {wire}", file=out)
    out.flush()


def print_summary(report: Report, out: TextIO) -> None:
    """The closing line: counts, and where the clauses are written."""
    print(
        f"{report.count(PASS)} passed, {report.count(FAIL)} failed, {report.count(SKIP)} skipped "
        "(clauses: docs/device-spec.md)",
        file=out,
    )


def run(args: argparse.Namespace) -> int:
    """Check the device at ``args.url``; the exit status (0 pass, 1 a clause failed, 2 unreachable)."""
    out = sys.stdout
    print(f"device-check {args.url}", file=out)
    try:
        report = asyncio.run(
            check_device(
                args.url,
                reply_wait=args.timeout,
                greeting_wait=args.greeting_wait,
                writes=not args.read_only,
                on_outcome=lambda outcome: print_outcome(outcome, out),
            )
        )
    except (OSError, ValueError) as exc:
        print(f"device-check: cannot reach the device: {exc}", file=sys.stderr)
        return 2
    if report.greeting:
        print(f"device: {report.greeting}", file=out)
    print_summary(report, out)
    return 1 if report.count(FAIL) else 0
