"""``psctl``: Get, Set, Listen and History on a Property Service gateway from the shell.

Exit codes: 0 success (also a Listen ended by --count, --duration or Ctrl-C);
1 the call failed (the gateway answered with an error status); 2 usage error
(bad arguments, a malformed -p or value); 3 the gateway cannot be reached;
130 interrupted by Ctrl-C (commands other than listen and top). With several
-t, the highest code of the targets.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import functools
import math
import os
import re
import sys
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from typing import Any

import shtab

from clients.aio import (
    DEFAULT_FAILOVER_LIMIT,
    DEFAULT_KEEPALIVE,
    DEFAULT_TARGET,
    DEFAULT_TIMEOUT,
    HEARTBEAT,
    SYNC,
    AsyncClient,
    Event,
    Mark,
    Selector,
    TimeArg,
)
from clients.cluster_view import ACTIONS, cluster_command
from clients.credentials import ENVIRONMENT, ClientCredentials
from clients.errors import GatewayUnreachable, NotFound, PropertyServiceError
from clients.psctl_output import FORMATS, RecordFile, RecordFileError, TargetOutput
from clients.psctl_top import StreamEnded, TopError, TopSource, run_top
from clients.values import Value, ValueFormatError
from services.kernel.model import ParameterModel, PropertyModel
from services.kernel.release import version_line

__all__ = ["EXIT_FAILED", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_UNREACHABLE", "EXIT_USAGE", "main"]

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_UNREACHABLE = 3
EXIT_INTERRUPTED = 130

#: The shells `psctl completion` writes a script for (shtab writes them from the argument parser).
COMPLETION_SHELLS = ("bash", "zsh", "fish")

#: Most Gets in flight at once when ``ls -l`` reads details.
_LS_CONCURRENCY = 32

#: Most gateways one command runs on (repeated -t): each is a channel and, for listen, a stream, and
#: their output shares one terminal. More is a usage error rather than a slow, unreadable run.
MAX_TARGETS = 32

#: --output-max-bytes and --output-keep by default: at most 4 x 64 MiB on disk for a listen left running.
_OUTPUT_MAX_BYTES = 64 * 2**20
_OUTPUT_KEEP = 3

_EPILOG = """\
examples:
  psctl ls                                    services known to the registry
  psctl ls -l                                 services with type, url and state
  psctl ls scout1 -l                          scout1's model: type, access, unit, range, doc
  psctl get scout1 location                   one value
  psctl get scout1 location.x location.y      several values, "path = value" lines
  psctl get swarm 'robots.*.location'         every match of a pattern, "path = value" lines
  psctl get registry find -p type=sensor      with a request parameter
  psctl set scout1 behaviors.moveto '<marker><location>(2 1 0 0 0 0)</location></marker>'
  psctl set files blob -p name=copy.md --file README.md   a file's bytes (or: ... blob @README.md)
  psctl get files blob -p name=copy.md --output -         a binary value (type bytes); -o FILE: into FILE
  psctl listen thermo1 data --count 10        ten readings of the sensor (it changes by itself)
  psctl listen scout1 location --duration 5   scout1's pose for five seconds
  psctl listen scout1 location --also scout2:location --min-interval 0.1 --duration 5
  psctl history scout1 location --since 60s   what the gateway kept of the last minute ([history])
  psctl --json get scout1 location            machine-readable output
  psctl -t gw1:50051 -t gw2:50051 get thermo1 data     on each gateway, each line tagged [gw1:50051]
  psctl --format jsonl listen thermo1 data --count 3      records: one JSON object a line (-o FILE: appended)
  psctl top scout1                            a live table of scout1's properties (q quits)
  psctl -t gw1:50051 -t gw2:50051 top thermo1          both gateways' thermo1 in one live table
  psctl cluster --devices                     the gateways of a cluster and who owns each device
  psctl cluster drain gw1                     gw1 hands its devices over (undrain gw1; rebalance)
  source <(psctl completion bash)             tab completion of commands and options (also zsh, fish)

The gateway address comes from --target, else $PSCTL_TARGET, else 127.0.0.1:50051. Several
addresses, comma-separated (-t gw1:50051,gw2:50051), or a gRPC name that stands for several
(dns:///gateways.local:50051): a call that cannot reach one gateway is made through the next, and
`listen --resume` moves to the next when its gateway dies or freezes; when none answers, the
error names each address tried (exit 3). -t given again (at most 32): the command runs on each
gateway at once; a gateway that fails is reported and the others go on, and the exit code is the
highest of theirs. --format jsonl: one JSON object a line (target, service, property, value, time,
kind); --output FILE appends them, moving FILE to FILE.1 at --output-max-bytes (0: no bound).
exit codes: 0 ok, 1 the call failed, 2 usage error, 3 gateway unreachable, 130 interrupted.
"""

_LISTEN_EPILOG = """\
--count counts events only (not the sync or heartbeat markers). A property that does not
change sends its current value and then nothing, so `listen scout1 location --count 10`
waits while scout1 stands still: add --duration to bound the wait.

examples:
  psctl listen thermo1 data --count 10                    ten readings (the sensor changes by itself)
  psctl listen scout1 location --duration 5               scout1's pose for five seconds
  psctl listen scout1 location --count 10 --duration 5    ten events or five seconds, whichever first
  psctl listen '*' location --min-interval 0.5 --json --duration 2
  psctl listen scout1 location --updates-only --heartbeat 1 --marks --duration 3
  psctl listen thermo1 data --count 5 --resume            five readings, across a gateway restart

The stream ends with exit code 0 at --count, --duration or Ctrl-C; a stream the gateway ends
(UNAVAILABLE "gateway shutting down", or any other error) exits 1 (3 when it cannot be reached).
"""


_HISTORY_EPILOG = """\
TIME is a duration before now (90s, 5m, 2h, 1d, 250ms) or an ISO-8601 time (2026-01-01T12:00:00Z;
without a zone: UTC). With more values in the range than --limit (or the gateway's default), the
oldest are printed and a last line says so: ask again with --since after the last one's time.

examples:
  psctl history scout1 location --since 60s             the last minute of scout1's pose
  psctl history '*' location --since 5m --until 1m      every robot's pose, from 5 to 1 minute ago
  psctl --json history bench value --limit 100          the oldest 100 kept values, as JSON lines
"""


_TOP_EPILOG = """\
examples:
  psctl top scout1                                    every property of scout1, live
  psctl top thermo1 --properties data,location        two properties
  psctl top swarm --properties 'robots.*.location'    every robot's pose in the group
  psctl top thermo1 --count 3 | cat                   piped: three plain tables, one per change
"""


class _UsageError(Exception):
    pass


#: A duration before now: a number and its unit.
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(ms|s|m|h|d)\s*$")
_DURATION_UNITS = {"ms": 0.001, "s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}


def _when(text: str) -> TimeArg:
    """A --since or --until: a duration before now, or an ISO-8601 time (naive: UTC)."""
    found = _DURATION.match(text)
    if found is not None:
        return timedelta(seconds=float(found.group(1)) * _DURATION_UNITS[found.group(2)])
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a duration before now like 60s, 5m or 2h, or an ISO-8601 time, got {text!r}"
        ) from None
    return when if when.tzinfo is not None else when.replace(tzinfo=UTC)


def _common_options(targets_dest: str) -> argparse.ArgumentParser:
    """The options every command takes, before or after its name. ``targets_dest``: where ``-t``
    gathers its targets; the ones before the command and the ones after it are kept apart (a
    subcommand's options land in a namespace of their own) and joined in :func:`_targets`."""
    # SUPPRESS defaults let the options appear before or after the command
    # without the subcommand's defaults overwriting what was given before it.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "-t",
        "--target",
        action="append",
        dest=targets_dest,
        metavar="HOST:PORT[,HOST:PORT...]",
        default=argparse.SUPPRESS,
        help="a gateway, or several comma-separated to fail over between; repeat -t to run the command "
        f"on each of several gateways (at most {MAX_TARGETS}) (default: $PSCTL_TARGET or {DEFAULT_TARGET})",
    )
    common.add_argument(
        "--timeout",
        type=_timeout,
        metavar="SECONDS",
        default=argparse.SUPPRESS,
        help=f"limit for each call, 0 for none (default: {DEFAULT_TIMEOUT:g})",
    )
    common.add_argument(
        "--keepalive",
        type=_timeout,
        metavar="SECONDS",
        default=argparse.SUPPRESS,
        help="seconds between keep-alive pings, and how long one may go unanswered before the gateway"
        f" counts as frozen; 0 for grpc's own (minutes) (default: {DEFAULT_KEEPALIVE:g})",
    )
    common.add_argument(
        "--failover-limit",
        type=_timeout,
        metavar="SECONDS",
        default=argparse.SUPPRESS,
        help="seconds `listen --resume` may go without reaching any gateway before it gives up;"
        f" 0 to keep trying (default: {DEFAULT_FAILOVER_LIMIT:g})",
    )
    common.add_argument(
        "--json", action="store_true", default=argparse.SUPPRESS, help="machine-readable JSON output"
    )
    common.add_argument(
        "--format",
        choices=FORMATS,
        default=argparse.SUPPRESS,
        help="text (default); json (as --json); jsonl: one JSON object a line with target, service, "
        "property, value, time and kind (get, ls, set, listen, history)",
    )
    common.add_argument(
        "-o",
        "--output",
        metavar="FILE",
        default=argparse.SUPPRESS,
        help="with --format jsonl: append the records to FILE (see --output-max-bytes). get without "
        "jsonl: write the value (one PATH) into FILE, bytes as they are ('-': to stdout); a binary "
        "value is never written to a terminal without it",
    ).complete = shtab.FILE  # type: ignore[attr-defined]  # shtab reads this attribute
    common.add_argument(
        "--output-max-bytes",
        type=_size,
        metavar="SIZE",
        default=argparse.SUPPRESS,
        help="when the --output file would grow past SIZE (bytes; k, M, G), it moves to FILE.1 and a new "
        f"one starts; 0 appends without a bound (default: {_OUTPUT_MAX_BYTES // 2**20}M)",
    )
    common.add_argument(
        "--output-keep",
        type=_count,
        metavar="N",
        default=argparse.SUPPRESS,
        help=f"moved --output files kept, FILE.1 (newest) to FILE.N (default: {_OUTPUT_KEEP})",
    )
    security = (
        ("--ca", "FILE", "PEM CA that signs the gateway's certificate; makes the channel TLS"),
        ("--cert", "FILE", "PEM client certificate, for mutual TLS (with --key)"),
        ("--key", "FILE", "private key of --cert"),
        ("--token", "TOKEN", "bearer token, sent as 'authorization: Bearer TOKEN' on every call"),
    )
    for flag, metavar, text in security:
        variable = ENVIRONMENT[flag[2:]]
        action = common.add_argument(
            flag, metavar=metavar, default=argparse.SUPPRESS, help=f"{text} (default: ${variable})"
        )
        if metavar == "FILE":
            action.complete = shtab.FILE  # type: ignore[attr-defined]  # shtab reads this attribute
    return common


def _param_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="request parameter (repeatable), e.g. -p frame=world",
    )


def _timeout(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"expected a number of seconds (0 for none), got {text!r}")
    return x


def _positive(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not x > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return x


def _count(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {text!r}")
    return n


def _size(text: str) -> int:
    found = re.fullmatch(r"\s*(\d+)\s*([kMG]?)i?B?\s*", text)
    if found is None:
        raise argparse.ArgumentTypeError(
            f"expected a size in bytes like 1000000, 512k, 64M or 1G, got {text!r}"
        )
    return int(found.group(1)) * {"": 1, "k": 2**10, "M": 2**20, "G": 2**30}[found.group(2)]


def build_parser() -> argparse.ArgumentParser:
    """The ``psctl`` argument parser."""
    common = _common_options("targets_after")
    parser = argparse.ArgumentParser(
        prog="psctl",
        description="Get, Set and Listen on the services behind a Property Service gateway.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[_common_options("targets")],
    )
    parser.add_argument("--version", action="version", version=version_line("psctl"))
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    ls = commands.add_parser(
        "ls",
        parents=[common],
        help="list services, or the properties of one service",
        description="Without SERVICE: the services the registry knows. With SERVICE: its properties.",
    )
    ls.add_argument("service", nargs="?", help="service whose properties to list")
    ls.add_argument(
        "-l", "--long", action="store_true", help="services: add type/url/state; a service: its typed model"
    )

    get = commands.add_parser(
        "get",
        parents=[common],
        help="read one or more properties",
        description='Read properties; one path prints its value, several print "path = value" lines.',
    )
    get.add_argument("service")
    get.add_argument("paths", nargs="+", metavar="PATH", help="dotted property path, e.g. location.x")
    _param_option(get)

    set_ = commands.add_parser(
        "set",
        parents=[common],
        help="write a property (or call a functional property)",
        description="Write VALUE (text; '-' reads it from stdin; @FILE sends FILE, as --file does; "
        "@@TEXT is the text @TEXT) and print what the service answered.",
    )
    set_.add_argument("service")
    set_.add_argument("path")
    set_.add_argument("value", nargs="?")
    set_.add_argument(
        "-f",
        "--file",
        metavar="FILE",
        help="send FILE's content instead of VALUE: its bytes for a binary property (type bytes), its "
        "UTF-8 text for a text one",
    )
    _param_option(set_)

    listen = commands.add_parser(
        "listen",
        parents=[common],
        help="print change events until --count, --duration or Ctrl-C",
        description=(
            "Print one line per event: time, service, property, value, and [conflated N], [gap] or "
            "[removed] markers. The current value comes first unless --updates-only. "
            "'*' in a path matches one segment."
        ),
        epilog=_LISTEN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    listen.add_argument("service")
    listen.add_argument("path")
    listen.add_argument(
        "--also",
        action="append",
        default=[],
        metavar="SERVICE:PATH",
        help="listen to a further property (repeatable)",
    )
    _param_option(listen)
    listen.add_argument("--updates-only", action="store_true", help="only changes, not the current values")
    listen.add_argument(
        "--min-interval", type=_positive, metavar="S", help="at most one event per property per S seconds"
    )
    listen.add_argument("--sample", type=_positive, metavar="S", help="every value once per S seconds")
    listen.add_argument(
        "--heartbeat", type=_positive, metavar="S", help="ask for a keep-alive after S quiet seconds"
    )
    listen.add_argument("--marks", action="store_true", help="also print the sync and heartbeat markers")
    listen.add_argument(
        "--count",
        type=_count,
        metavar="N",
        help="exit after N events (markers do not count; waits while nothing changes, see below)",
    )
    listen.add_argument("--duration", type=_positive, metavar="S", help="exit after S seconds")
    listen.add_argument(
        "--resume",
        action="store_true",
        help="when the gateway goes away (UNAVAILABLE, or a keep-alive unanswered), listen again, "
        "through the next of several --target addresses; the first event after that is marked [gap]; "
        "exits 3 naming every address tried when none answers for 30 s",
    )
    listen.add_argument(
        "--separate-stream",
        action="store_true",
        help="listen on a Listen stream of its own rather than inside a Session (the default, which "
        "costs the gateway a tenth of the memory)",
    )
    history = commands.add_parser(
        "history",
        parents=[common],
        help="print the values the gateway kept of a property (its [history])",
        description=(
            "Print the kept values of PATH of SERVICE ('*' for the service or a path segment: every "
            "match), oldest first, one line each as listen prints them. The gateway keeps the "
            "properties its [history] selectors name (docs/recording.md)."
        ),
        epilog=_HISTORY_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    history.add_argument("service")
    history.add_argument("path")
    history.add_argument(
        "--since",
        type=_when,
        metavar="TIME",
        help="from TIME on: a duration before now (60s, 5m, 2h, 1d) or ISO-8601",
    )
    history.add_argument("--until", type=_when, metavar="TIME", help="before TIME (the same forms)")
    history.add_argument(
        "--limit", type=_count, default=0, metavar="N", help="at most N values (default: the gateway's)"
    )
    cluster = commands.add_parser(
        "cluster",
        parents=[common],
        help="the gateways of a cluster, who owns what; drain, undrain, rebalance",
        description="Without ACTION: every gateway of the cluster (address, version, health, state, "
        "devices owned, load, lease), as the registry's 'cluster' shows it. drain GATEWAY: it hands "
        "its devices over and takes no new ones; undrain GATEWAY; rebalance: every gateway hands "
        "devices over until the loads are within the spread (admin actions, by the rules).",
    )
    cluster.add_argument("action", nargs="?", default="show", choices=sorted(ACTIONS), help="show by default")
    cluster.add_argument("gateway", nargs="?", help="the gateway to drain or undrain")
    cluster.add_argument("--devices", action="store_true", help="also each device's owner and since when")
    cluster.add_argument("--watch", action="store_true", help="show the view again each time it changes")
    cluster.add_argument("--count", type=_count, metavar="N", help="with --watch: exit after N views")
    top = commands.add_parser(
        "top",
        parents=[common],
        help="a live table of a service's properties, updated as they change",
        description="Show SERVICE's properties as a table that changes in place as they do (a Listen):\n"
        "name, value (shortened to the terminal's width), unit, age since the last change, and how\n"
        "many changes were seen; with several -t, the gateway first. q or Ctrl-C quits. Piped, it\n"
        "prints a plain table whenever values changed, at most once per --interval.",
        epilog=_TOP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    top.add_argument("service")
    top.add_argument(
        "--properties",
        metavar="PATH[,PATH...]",
        help="the properties to show, comma-separated; '*' matches one segment (robots.*.location) "
        "(default: every property of SERVICE that can be listened to)",
    )
    top.add_argument(
        "--interval", type=_positive, default=1.0, metavar="S", help="piped: at most one table per S seconds"
    )
    top.add_argument("--count", type=_count, metavar="N", help="piped: exit after N tables")
    top.add_argument("--duration", type=_positive, metavar="S", help="exit after S seconds")
    completion = commands.add_parser(
        "completion",
        help="print a shell's tab-completion script for psctl",
        description="Print a script that completes psctl's commands and options; load it with "
        "`source <(psctl completion bash)` (zsh: the same; fish: `psctl completion fish | source`), "
        "or put it where the shell loads completions from (docs/client.md).",
    )
    completion.add_argument("shell", choices=COMPLETION_SHELLS, help="the shell: bash, zsh or fish")
    return parser


def _parse_params(items: Sequence[str]) -> dict[str, str]:
    params: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise _UsageError(f"bad parameter {item!r}: use NAME=VALUE, e.g. -p frame=world")
        params[name] = value
    return params


def _parse_selector(text: str) -> Selector:
    service, sep, path = text.partition(":")
    if not sep or not service or not path:
        raise _UsageError(f"bad selector {text!r}: use SERVICE:PATH, e.g. scout2:location")
    return (service, path)


async def _gather_optional(client: AsyncClient, refs: list[tuple[str, str]]) -> list[str | None]:
    """Values of ``refs`` (as text: a binary one as ``<N bytes>``), None for each that does not exist."""
    limit = asyncio.Semaphore(_LS_CONCURRENCY)

    async def one(service: str, prop: str) -> str | None:
        async with limit:
            try:
                return _shown(await client.get(service, prop))
            except NotFound:
                return None

    return list(await asyncio.gather(*(one(s, p) for s, p in refs)))


def _type_text(prop: PropertyModel) -> str:
    if prop.media_type:
        return f"{prop.type}({prop.media_type})"
    return f"{prop.type}[{prop.length}]" if prop.length else prop.type


def _range_text(prop: PropertyModel) -> str:
    if prop.max_size:
        return f"at most {prop.max_size} bytes"
    if prop.choices:
        return "|".join(prop.choices)
    if prop.minimum is None and prop.maximum is None:
        return ""
    low = "" if prop.minimum is None else f"{prop.minimum:g}"
    high = "" if prop.maximum is None else f"{prop.maximum:g}"
    return f"{low}..{high}"


def _parameter_json(param: ParameterModel) -> dict[str, Any]:
    return {"type": param.type, "required": param.required, "default": param.default, "doc": param.doc}


def _property_json(prop: PropertyModel) -> dict[str, Any]:
    return {
        "name": prop.name,
        "type": prop.type,
        "length": prop.length,
        "access": prop.access.value,
        "unit": prop.unit,
        "minimum": prop.minimum,
        "maximum": prop.maximum,
        "choices": list(prop.choices),
        "doc": prop.doc,
        "gui": prop.gui,
        "media_type": prop.media_type,
        "max_size": prop.max_size,
        "value": None if prop.value is None else {"name": prop.value.name, **_parameter_json(prop.value)},
        "parameters": {p.name: _parameter_json(p) for p in prop.parameters},
    }


async def _ls_model(client: AsyncClient, service: str, out: TargetOutput) -> int:
    """``ls -l SERVICE``: the service's model (the Describe RPC) as a table, JSON or records."""
    model = await client.describe(service)
    if out.as_records:
        for p in model.properties:
            out.record("property", service, p.name, extra={"model": _property_json(p)})
    elif out.as_json:
        out.json([_property_json(p) for p in model.properties])
    elif model.properties:
        header = ["NAME", "TYPE", "ACCESS", "UNIT", "RANGE", "DOC"]
        rows = [
            [p.name, _type_text(p), p.access.value, p.unit or "-", _range_text(p) or "-", p.doc or "-"]
            for p in model.properties
        ]
        out.table([header, *rows])
    return EXIT_OK


async def _ls(client: AsyncClient, args: argparse.Namespace, out: TargetOutput) -> int:
    if args.service is not None and args.long:
        return await _ls_model(client, args.service, out)
    if args.service is None:
        names = await client.services()
    else:
        names = await client.properties(args.service)
    if not args.long:
        if out.as_records:
            for name in names:
                if args.service is None:
                    out.record("service", name, None)
                else:
                    out.record("property", args.service, name)
        elif out.as_json:
            out.json(names)
        else:
            for name in names:
                out.line(name)
        return EXIT_OK
    columns = ("type", "url", "state")
    refs = [("registry", f"services.{name}.{c}") for name in names for c in columns]
    values = await _gather_optional(client, refs)
    n = len(columns)
    details = [dict(zip(columns, values[i * n : (i + 1) * n], strict=True)) for i in range(len(names))]
    if out.as_records:
        for name, d in zip(names, details, strict=True):
            out.record("service", name, None, extra=d)
    elif out.as_json:
        out.json([{"name": name, **d} for name, d in zip(names, details, strict=True)])
    elif names:
        header = ["NAME", *(c.upper() for c in columns)]
        rows = [[name, *(d[c] or "-" for c in columns)] for name, d in zip(names, details, strict=True)]
        out.table([header, *rows])
    return EXIT_OK


async def _media_type(client: AsyncClient, service: str, path: str, params: dict[str, str]) -> str:
    """``PATH.media_type`` of a binary property (asked with the request's parameters: a storage
    service's ``blob`` names its type by the file's ``name``); "" when the service does not say."""
    try:
        media = await client.get(service, f"{path}.media_type", **params)
    except PropertyServiceError:
        return ""
    return media if isinstance(media, str) else ""


def _shown(value: Value, media_type: str = "") -> str:
    """A value on a line: text as it is, bytes as ``<N bytes MEDIA>``."""
    if isinstance(value, str):
        return value
    return f"<{len(value)} bytes {media_type}>" if media_type else f"<{len(value)} bytes>"


def _json_value(value: Value) -> dict[str, str]:
    """A value in JSON: ``{"value": TEXT}``, or ``{"data": BASE64}`` for bytes."""
    if isinstance(value, str):
        return {"value": value}
    return {"data": base64.b64encode(value).decode("ascii")}


def _write_output(name: str, value: Value) -> int:
    """Write ``value`` into file ``name`` ('-': stdout), bytes as they are; the bytes written."""
    data = value if isinstance(value, bytes) else value.encode()
    if name == "-":
        sys.stdout.flush()
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return len(data)
    try:
        with open(name, "wb") as out:
            out.write(data)
    except OSError as e:
        raise _UsageError(f"--output {name}: {e.strerror}") from None
    return len(data)


async def _print_binary(
    client: AsyncClient, service: str, path: str, params: dict[str, str], value: bytes
) -> None:
    """A binary value without --output: to a pipe or a file as it is, never to a terminal."""
    if sys.stdout.isatty():
        media = await _media_type(client, service, path, params)
        kind = f" of {media}" if media else ""
        raise _UsageError(
            f"{service} {path} is binary ({len(value)} bytes{kind}): not written to a terminal; "
            f"use --output FILE (or --output - to write it here anyway)"
        )
    _write_output("-", value)


async def _readings(
    client: AsyncClient, service: str, path: str, params: dict[str, str]
) -> list[tuple[str, Value, datetime | None]]:
    """``(path, value, time)`` of a PATH: one with its source time, or every match of a pattern
    (whose time the gateway does not give: None)."""
    if "*" in path:
        return [(p, v, None) for p, v in (await client.get_matching(service, path, **params)).items()]
    reading = await client.get_with_time(service, path, **params)
    return [(path, reading.value, reading.time)]


async def _get_records(
    client: AsyncClient, service: str, paths: list[str], params: dict[str, str], out: TargetOutput
) -> int:
    """``get`` in ``--format jsonl``: a ``value`` record per path (per match of a pattern)."""
    found = await asyncio.gather(*(_readings(client, service, path, params) for path in paths))
    for readings in found:
        for path, value, time in readings:
            out.record("value", service, path, value, time=time)
    return EXIT_OK


async def _get(client: AsyncClient, args: argparse.Namespace, out: TargetOutput) -> int:
    params = _parse_params(args.param)
    service: str = args.service
    paths: list[str] = args.paths
    if out.as_records:
        return await _get_records(client, service, paths, params, out)
    output: str | None = getattr(args, "output", None)
    if output is not None:
        if len(paths) != 1 or "*" in paths[0]:
            raise _UsageError("--output takes the value of one PATH (no pattern)")
        value = await client.get(service, paths[0], **params)
        size = _write_output(output, value)
        if out.as_json and output != "-":
            out.json({"service": service, "property": paths[0], "output": output, "size": size})
        return EXIT_OK
    values: list[Value]
    if any("*" in path for path in paths):
        # A pattern reads a snapshot of every match: "path = value" lines, one per match.
        found: dict[str, Value] = {}
        for path in paths:
            if "*" in path:
                found.update(await client.get_matching(service, path, **params))
            else:
                found[path] = await client.get(service, path, **params)
        paths, values = list(found), list(found.values())
        if not out.as_json and len(paths) == 1:
            out.line(f"{paths[0]} = {_shown(values[0])}")
            return EXIT_OK
    elif len(paths) == 1:
        values = [await client.get(service, paths[0], **params)]
    else:
        values = await client.get_many([(service, path, params) for path in paths])
    if out.as_json:
        objs = [
            {"service": service, "property": p, **_json_value(v)} for p, v in zip(paths, values, strict=True)
        ]
        out.json(objs[0] if len(objs) == 1 else objs)
    elif len(paths) == 1:
        value = values[0]
        if isinstance(value, bytes) and not out.tagged:
            await _print_binary(client, service, paths[0], params, value)
        else:
            # Several targets share the output: a binary value shows as <N bytes>, as in a list.
            out.line(_shown(value))
    else:
        for path, value in zip(paths, values, strict=True):
            out.line(f"{path} = {_shown(value)}")
    return EXIT_OK


def _read_file(name: str) -> bytes:
    try:
        with open(name, "rb") as f:
            return f.read()
    except OSError as e:
        raise _UsageError(f"cannot read {name!r}: {e.strerror}") from None


async def _file_value(client: AsyncClient, service: str, path: str, name: str) -> Value:
    """FILE's content as the property takes it: bytes for a binary one (or one the service does
    not describe), UTF-8 text for a text one."""
    data = _read_file(name)
    try:
        model = await client.describe(service)
    except PropertyServiceError:
        return data
    prop = next((p for p in model.properties if p.name == path), None)
    if prop is None:
        return data
    word = prop.value.type if prop.value is not None else prop.type
    if word in ("bytes", "unknown"):
        return data
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise _UsageError(
            f"{service} {path} takes text (type {word}), and {name!r} is not UTF-8 text"
        ) from None


async def _set_value(client: AsyncClient, args: argparse.Namespace) -> Value:
    """What ``set`` sends: VALUE, stdin ('-'), or a file (--file FILE, @FILE)."""
    text: str | None = args.value
    if args.file is not None:
        if text is not None:
            raise _UsageError("give VALUE or --file FILE, not both")
        return await _file_value(client, args.service, args.path, args.file)
    if text is None:
        raise _UsageError("set needs a VALUE (or --file FILE)")
    if text == "-":
        return _stdin_text()
    if text.startswith("@@"):
        return text[1:]
    if text.startswith("@") and len(text) > 1:
        return await _file_value(client, args.service, args.path, text[1:])
    return text


@functools.cache
def _stdin_text() -> str:
    """``set ... -``: stdin, read once, whatever the number of targets that are sent it."""
    return sys.stdin.read().rstrip("\n")


async def _set(client: AsyncClient, args: argparse.Namespace, out: TargetOutput) -> int:
    params = _parse_params(args.param)
    value = await _set_value(client, args)
    answer = await client.set(args.service, args.path, value, **params)
    if out.as_records:
        out.record("set", args.service, args.path, answer)
    elif out.as_json:
        out.json({"service": args.service, "property": args.path, **_json_value(answer)})
    elif isinstance(answer, bytes):
        out.line(_shown(answer))
    elif answer:
        out.line(answer)
    return EXIT_OK


def _clock(t: datetime) -> str:
    return t.astimezone().strftime("%H:%M:%S.%f")[:-3]


def _event_line(ev: Event) -> str:
    line = f"{_clock(ev.time)} {ev.service} {ev.property} = {_shown(ev.value)}"
    if ev.conflated:
        line += f" [conflated {ev.conflated}]"
    if ev.gap:
        line += " [gap]"
    if ev.removed:
        line += " [removed]"
    return line


def _event_json(ev: Event) -> dict[str, Any]:
    return {
        "service": ev.service,
        "property": ev.property,
        **_json_value(ev.value),
        "sequence": ev.sequence,
        "time": ev.time.isoformat(),
        "conflated": ev.conflated,
        "gap": ev.gap,
        "removed": ev.removed,
    }


def _print_event(ev: Event, out: TargetOutput, kind: str) -> None:
    """A listened (``kind`` "event") or kept ("history") event, in the output's format."""
    if out.as_records:
        extra = {"sequence": ev.sequence, "conflated": ev.conflated, "gap": ev.gap, "removed": ev.removed}
        out.record(kind, ev.service, ev.property, ev.value, time=ev.time, extra=extra)
    elif out.as_json:
        out.json(_event_json(ev))
    else:
        out.line(_event_line(ev))


async def _listen(client: AsyncClient, args: argparse.Namespace, out: TargetOutput) -> int:
    more = [_parse_selector(s) for s in args.also]
    stream = client.listen(
        args.service,
        args.path,
        *more,
        params=_parse_params(args.param),
        updates_only=args.updates_only,
        min_interval=args.min_interval,
        sample_interval=args.sample,
        heartbeat=args.heartbeat,
        marks=True,
        resume=args.resume,
    )
    seen = 0
    try:
        async with asyncio.timeout(args.duration):
            async for item in stream:
                if isinstance(item, Mark):
                    if args.marks:
                        _print_mark(item, out)
                    continue
                _print_event(item, out, "event")
                seen += 1
                if args.count is not None and seen >= args.count:
                    return EXIT_OK
    except TimeoutError:
        return EXIT_OK  # --duration elapsed
    finally:
        await stream.aclose()
    # Neither --count nor --duration ended it, nor Ctrl-C: the gateway did (an error raises above).
    out.error(f"the gateway ended the stream after {seen} event{'' if seen == 1 else 's'}")
    return EXIT_FAILED


async def _history(client: AsyncClient, args: argparse.Namespace, out: TargetOutput) -> int:
    kept = await client.history(args.service, args.path, since=args.since, until=args.until, limit=args.limit)
    for event in kept:
        _print_event(event, out, "history")
    if kept.truncated:
        if out.as_records:
            out.record("truncated", args.service, args.path)
        elif out.as_json:
            out.json({"truncated": True})
        else:
            out.line(
                f"-- {len(kept)} shown, more lie in the range: ask again with --since after the last one"
            )
    return EXIT_OK


async def _top(
    args: argparse.Namespace,
    *,
    targets: list[str],
    clients: list[AsyncClient],
    codes: list[int],
) -> int:
    """``top`` on every target in one table; a target that fails is reported, the others go on."""
    several = len(targets) > 1
    outs = {target: TargetOutput(target, tagged=several) for target in targets}
    paths = [p.strip() for p in args.properties.split(",") if p.strip()] if args.properties else None

    def report(target: str, error: Exception) -> None:
        outs[target].error(str(error))
        codes.append(_exit_code(error))

    try:
        await run_top(
            [TopSource(target, client) for target, client in zip(targets, clients, strict=True)],
            args.service,
            paths,
            interval=args.interval,
            count=args.count,
            duration=args.duration,
            print_line=TargetOutput(targets[0]).line,  # a table's lines, tagged by its TARGET column
            report=report,
        )
    except TopError as e:
        raise _UsageError(str(e)) from None
    return max(codes, default=EXIT_OK)


def _exit_code(error: Exception) -> int:
    """The exit code of a target that failed with ``error``."""
    if isinstance(error, GatewayUnreachable):
        return EXIT_UNREACHABLE
    if isinstance(error, StreamEnded | PropertyServiceError):
        return EXIT_FAILED
    return EXIT_USAGE


def _print_mark(mark: Mark, out: TargetOutput) -> None:
    if out.as_records:
        out.record(str(mark.value), None, None)
    elif out.as_json:
        out.json({"mark": mark.value, "time": datetime.now().astimezone().isoformat()})
    elif mark is SYNC:
        out.line("-- sync: current values sent, changes follow")
    elif mark is HEARTBEAT:
        out.line(f"{_clock(datetime.now())} -- heartbeat")


async def _cluster(client: AsyncClient, args: argparse.Namespace, out: TargetOutput) -> int:
    takes_gateway = ACTIONS[args.action]
    if takes_gateway and not args.gateway:
        raise _UsageError(
            f"cluster {args.action} takes the id of a gateway, e.g. psctl cluster {args.action} gw1"
        )
    if not takes_gateway and args.gateway:
        raise _UsageError(f"cluster {args.action} takes no gateway")
    await cluster_command(
        client,
        args.action,
        args.gateway,
        devices=args.devices,
        watch=args.watch,
        count=args.count,
        as_json=out.as_json,
        table=out.table,
        out=out.line,
    )
    return EXIT_OK


_COMMANDS = {
    "ls": _ls,
    "get": _get,
    "set": _set,
    "listen": _listen,
    "history": _history,
    "cluster": _cluster,
}


def _credentials(args: argparse.Namespace) -> ClientCredentials:
    """``--ca --cert --key --token``, each falling back to its PSCTL_ variable; files must exist."""
    given = {name: getattr(args, name, None) for name in ENVIRONMENT}
    credentials = ClientCredentials.from_environment(os.environ, **given)
    for name in ("ca", "cert", "key"):
        path = getattr(credentials, name)
        if path and not os.path.isfile(path):
            raise _UsageError(f"--{name} ({ENVIRONMENT[name]}): no such file {path!r}")
    return credentials


async def _run_target(
    args: argparse.Namespace,
    *,
    target: str,
    call_timeout: float | None,
    credentials: ClientCredentials,
    out: TargetOutput,
    codes: list[int],
) -> int:
    """The command on one target; its failure is reported through ``out`` and leaves the others
    going. Its exit code is also added to ``codes`` as soon as it is known."""
    code = EXIT_FAILED
    try:
        async with _client(args, target, call_timeout, credentials) as client:
            code = await _COMMANDS[args.command](client, args, out)
    except (PropertyServiceError, _UsageError, ValueFormatError, ValueError) as e:
        out.error(str(e))
        code = _exit_code(e)
    codes.append(code)
    return code


def _client(
    args: argparse.Namespace, target: str, call_timeout: float | None, credentials: ClientCredentials
) -> AsyncClient:
    return AsyncClient(
        target,
        timeout=call_timeout,
        credentials=credentials,
        separate_listens=getattr(args, "separate_stream", False),
        keepalive=getattr(args, "keepalive", DEFAULT_KEEPALIVE) or None,
        failover_limit=getattr(args, "failover_limit", DEFAULT_FAILOVER_LIMIT) or None,
    )


async def _run(
    args: argparse.Namespace,
    *,
    targets: list[str],
    call_timeout: float | None,
    output_format: str,
    records: RecordFile | None,
    codes: list[int],
) -> int:
    """The command on every target at once. With several, a command that ends by itself prints
    each target's results when it is done, in the order of -t; a listen's lines come as they happen.
    The exit code: 0 when every target succeeded, else the highest of theirs."""
    credentials = _credentials(args)
    if args.command == "top":
        async with contextlib.AsyncExitStack() as opened:
            clients = [
                await opened.enter_async_context(_client(args, target, call_timeout, credentials))
                for target in targets
            ]
            return await _top(args, targets=targets, clients=clients, codes=codes)
    several = len(targets) > 1
    held = several and args.command != "listen"
    outs = [
        TargetOutput(target, tagged=several, held=held, format=output_format, records=records)
        for target in targets
    ]
    tasks = [
        asyncio.create_task(
            _run_target(
                args, target=target, call_timeout=call_timeout, credentials=credentials, out=out, codes=codes
            )
        )
        for target, out in zip(targets, outs, strict=True)
    ]
    try:
        for out, task in zip(outs, tasks, strict=True):
            await task
            out.release()
    finally:
        for task in tasks:
            task.cancel()
    return max(codes, default=EXIT_OK)


def completion_script(shell: str) -> str:
    """The tab-completion script of psctl for ``shell`` (one of :data:`COMPLETION_SHELLS`)."""
    return str(shtab.complete(build_parser(), shell=shell))


def _error(message: str) -> None:
    print(f"error: {message}", file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``psctl`` with ``argv`` (default: the process arguments); return the exit code."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if args.command == "completion":
        if extra:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        print(completion_script(args.shell), end="")
        return EXIT_OK
    if extra:
        # argparse gives a set's optional VALUE up once an option comes between it and the path
        # (`psctl set files blob -p name=a.txt hello`): it is still the value.
        if args.command == "set" and args.value is None and len(extra) == 1 and not extra[0].startswith("-"):
            args.value = extra[0]
        else:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
    timeout: float | None = getattr(args, "timeout", DEFAULT_TIMEOUT)
    if timeout is not None and timeout <= 0:
        timeout = None
    codes: list[int] = []
    records: RecordFile | None = None
    try:
        targets = _targets(args)
        output_format = _output_format(args, len(targets))
        _check_arguments(args)
        if output_format == "jsonl" and getattr(args, "output", None) is not None:
            records = _record_file(args)
        return asyncio.run(
            _run(
                args,
                targets=targets,
                call_timeout=timeout,
                output_format=output_format,
                records=records,
                codes=codes,
            )
        )
    except KeyboardInterrupt:
        if args.command in ("listen", "top"):
            # Ctrl-C ends a listen well; a target that failed before it did not.
            return max(codes, default=EXIT_OK)
        return EXIT_INTERRUPTED
    except (_UsageError, ValueFormatError, ValueError) as e:
        _error(str(e))
        return EXIT_USAGE
    except RecordFileError as e:
        _error(str(e))
        return EXIT_FAILED
    except BrokenPipeError:
        # The reader went away (e.g. `psctl listen ... | head`); keep the interpreter's final flush quiet.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    finally:
        if records is not None:
            records.close()


def _targets(args: argparse.Namespace) -> list[str]:
    """The gateways to run on: every -t, before the command and after it, in order; else
    $PSCTL_TARGET, else the default. Each may itself be comma-separated addresses to fail over between."""
    given: list[str] = [*getattr(args, "targets", []), *getattr(args, "targets_after", [])]
    if not given:
        return [os.environ.get("PSCTL_TARGET") or DEFAULT_TARGET]
    targets = [t.strip() for t in given]
    if any(not t for t in targets):
        raise _UsageError("-t needs an address, e.g. -t 127.0.0.1:50051")
    if len(targets) > MAX_TARGETS:
        raise _UsageError(f"{len(targets)} targets: at most {MAX_TARGETS} in one command")
    twice = sorted({t for t in targets if targets.count(t) > 1})
    if twice:
        raise _UsageError(f"-t {twice[0]} is given twice")
    if len(targets) > 1 and args.command == "cluster":
        raise _UsageError(f"{args.command} shows one gateway's view: give one -t")
    return targets


def _output_format(args: argparse.Namespace, n_targets: int) -> str:
    """--format, or json for --json; what each command can print."""
    as_json = bool(getattr(args, "json", False))
    chosen: str = getattr(args, "format", "json" if as_json else "text")
    if as_json and chosen != "json":
        raise _UsageError(f"--json and --format {chosen} disagree: give one")
    if chosen != "text" and args.command == "top":
        raise _UsageError("top is a view for people: text only (listen --format jsonl gives records)")
    if chosen == "jsonl" and args.command == "cluster":
        raise _UsageError(
            "cluster prints JSON with --json; --format jsonl is for ls, get, set, listen, history"
        )
    output = getattr(args, "output", None)
    if output is not None and chosen != "jsonl" and args.command != "get":
        raise _UsageError(
            f"--output FILE takes --format jsonl records; {args.command} has no other use for it"
        )
    if output is not None and chosen != "jsonl" and n_targets > 1:
        raise _UsageError("--output FILE takes the value of one target; with several -t, use --format jsonl")
    if output == "-" and chosen == "jsonl":
        raise _UsageError("--output - with --format jsonl: the records go to stdout without --output")
    return chosen


def _check_arguments(args: argparse.Namespace) -> None:
    """Malformed -p and --also: said once, before any gateway is asked, not once per target."""
    _parse_params(getattr(args, "param", []))
    for selector in getattr(args, "also", []):
        _parse_selector(selector)


def _record_file(args: argparse.Namespace) -> RecordFile:
    name: str = args.output
    try:
        return RecordFile(
            name,
            max_bytes=getattr(args, "output_max_bytes", _OUTPUT_MAX_BYTES),
            keep=getattr(args, "output_keep", _OUTPUT_KEEP),
        )
    except OSError as e:
        raise _UsageError(f"--output {name}: {e.strerror}") from None


if __name__ == "__main__":
    raise SystemExit(main())
