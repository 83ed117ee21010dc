"""Plugs ``psgateway device`` into the gateway CLI (listed in ``gateway.cli.SUBCOMMAND_MODULES``)."""

from __future__ import annotations

from typing import Any

from gateway import device_cli


def add_subcommand(subparsers: Any) -> None:
    """Add the ``device`` subcommand."""
    device_cli.add_parser(subparsers)
