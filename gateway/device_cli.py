"""``psgateway device``: serve a Python service over the line protocol, standing in for a microcontroller.

psgateway device --service sim-robot --tcp 127.0.0.1:7001
psgateway device --service sim-sensor --serial /dev/pts/3 --baud 115200 --name therm1
psgateway device --service sim-robot --pty     # prints: serial port /dev/pts/N
"""

from __future__ import annotations

import argparse
from typing import Any

from services.device import cli as device_command


def add_parser(subparsers: Any) -> None:
    """Add the ``device`` subcommand to ``subparsers`` (from ``ArgumentParser.add_subparsers``)."""
    parser: argparse.ArgumentParser = subparsers.add_parser(
        "device",
        help="serve a service over the line protocol on a TCP port, a serial port or a new pty",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    device_command.add_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the device until SIGINT/SIGTERM; the exit status."""
    return device_command.run(args)
