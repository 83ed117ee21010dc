"""``psgateway``: run the Property Service gateway.

Subcommands: ``serve`` and ``check-config`` (here), ``device`` (:mod:`gateway.device_cli`),
``device-check`` (:mod:`gateway.device_check_cli`), ``export-ros2`` (:mod:`gateway.export_cli`)
and ``tls`` (:mod:`gateway.tls_cli`); each adds its parser and sets
``func`` (``args -> exit code``) with ``set_defaults``.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import logging
import sys
from collections.abc import Sequence
from typing import Any

# First among the gateway's imports: it sets GRPC_VERBOSITY before anything imports grpc.
import gateway.grpc_core_logs  # noqa: F401
from gateway import device_check_cli, device_cli, export_cli, tls_cli
from gateway.allocator import return_large_blocks
from gateway.config import Config, ConfigError, default_config, load_config, load_config_partly
from gateway.logs import LOG_FORMATS, setup_logging
from services.kernel.release import version_line

#: Exit code of a gateway that cannot start as configured: a config error or a port in use.
EXIT_CONFIG = 2

#: Allocations (less frees) between the collector's young collections in a serving gateway;
#: CPython's default is 700. A gateway holding thousands of devices keeps requests, PINGs and
#: timers alive for milliseconds to seconds, so at 700 many of them outlive two young collections
#: and reach the oldest generation, whose collections then come every few seconds and each walk
#: every device's objects: 15 of them (9.7 s) while 10,000 devices registered, against none at
#: 50,000, where the rate stayed flat from 1,000 to 10,000 devices (docs/performance.md, part (h)).
#: At most this many objects wait for a young collection: a few MiB.
YOUNG_COLLECTION_THRESHOLD = 50_000

EXAMPLES = """\
examples:
  psgateway                                   serve the demo (robots, a sensor, a swarm, files, missions,
                                              cameras, an environment model)
                                              on 127.0.0.1:50051, its console on http://127.0.0.1:8080/
  psgateway serve --config site.toml          serve the services a config file lists
  psgateway serve --listen 127.0.0.1:0        pick a free port (printed as "listening on HOST:PORT")
  psgateway serve --http 127.0.0.1:8080       the HTTP/JSON API and browser console on that port ('' = off)
  psgateway serve --listen 127.0.0.1:50052 --http 127.0.0.1:8081
                                              the demo beside a gateway that holds the usual ports
  psgateway serve --log-format json --log-level debug
                                              one JSON object a log line, with request ids
  psgateway check-config site.toml            check a config file and exit (0 = fine, 2 = errors)
  psgateway device-check tcp://10.0.0.7:7000  check a device against docs/device-spec.md (0 = conforms)
  psgateway tls init certs --client operator  a CA, server and client certificates for TLS, and the
                                              config lines and psctl flags that use them

then, from another shell:
  grpcurl -plaintext 127.0.0.1:50051 list
  curl -s 127.0.0.1:8080/api/v1/services
  grpcurl -plaintext -d '{"service":"scout1","property":"location"}' \\
      127.0.0.1:50051 propertyservice.v1.PropertyService/Get
  grpcurl -plaintext -d '{"service":"rover1"}' 127.0.0.1:50051 grpc.health.v1.Health/Check
  curl -s 127.0.0.1:8080/metrics              Prometheus metrics (docs/metrics.md)
"""


def add_subcommand(subparsers: Any) -> None:
    """The gateway's own subcommands: ``serve`` and ``check-config``."""
    serve = subparsers.add_parser(
        "serve",
        help="run the gateway (the default)",
        description="Run the gateway until SIGTERM or Ctrl-C.",
    )
    _serve_arguments(serve)
    serve.set_defaults(func=_serve)

    check = subparsers.add_parser(
        "check-config",
        help="check a config file",
        description="Read a config file, check every key, and build (without starting) every service.",
    )
    check.add_argument("file", help="the TOML config file")
    check.set_defaults(func=_check_config)


def _serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="TOML config file (default: the built-in demo)")
    parser.add_argument(
        "--listen", metavar="HOST:PORT", help="override gateway.listen (port 0 = a free port)"
    )
    parser.add_argument(
        "--http",
        metavar="HOST:PORT",
        help="override http.listen: the HTTP/JSON front end and browser console (port 0 = a free port;"
        " '' = off)",
    )
    parser.add_argument(
        "--log-level",
        metavar="LEVEL",
        choices=("debug", "info", "warning", "error", "critical"),
        help="override gateway.log_level: debug, info, warning, error, critical",
    )
    parser.add_argument(
        "--log-format",
        choices=LOG_FORMATS,
        help="override gateway.log_format: text, or json (one object a line)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``psgateway`` argument parser with every installed subcommand."""
    parser = argparse.ArgumentParser(
        prog="psgateway",
        description=(
            "The Property Service gateway: Get, Set and Listen on robots and sensors over gRPC,\n"
            "and over HTTP/JSON with a browser console."
        ),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=version_line("psgateway"))
    subparsers = parser.add_subparsers(title="commands", metavar="COMMAND")
    add_subcommand(subparsers)
    device_cli.add_parser(subparsers)
    device_check_cli.add_parser(subparsers)
    export_cli.add_parser(subparsers)
    tls_cli.add_parser(subparsers)
    return parser


def _load(args: argparse.Namespace) -> Config:
    config = load_config(args.config) if args.config else default_config()
    return config.with_overrides(
        listen=args.listen, log_level=args.log_level, http=args.http, log_format=args.log_format
    )


def _config_errors(exc: ConfigError) -> int:
    for problem in exc.problems:
        print(f"psgateway: config error: {problem}", file=sys.stderr)
    return EXIT_CONFIG


def _serve(args: argparse.Namespace) -> int:
    from gateway.app import serve
    from gateway.ports import PortInUse
    from services.kernel.errors import PropertyError

    try:
        config = _load(args)
    except ConfigError as exc:
        return _config_errors(exc)
    setup_logging(config.gateway.log_level, config.gateway.log_format)
    log = logging.getLogger("gateway")
    log.info("starting gateway from %s", config.source)
    _, middle, oldest = gc.get_threshold()
    gc.set_threshold(YOUNG_COLLECTION_THRESHOLD, middle, oldest)
    return_large_blocks()  # what slow readers of large values held is given back (gateway.allocator)
    try:
        return asyncio.run(serve(config))
    except KeyboardInterrupt:
        return 0
    except ConfigError as exc:
        return _config_errors(exc)
    except PortInUse as exc:
        print(f"psgateway: cannot start: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except PropertyError as exc:
        log.error("cannot start: %s", exc.message)
        return 1
    except Exception:
        log.exception("cannot start")
        return 1


def _check_config(args: argparse.Namespace) -> int:
    from gateway.backends import open_backend
    from gateway.engine.router import Router
    from services.apps.catalog import build
    from services.kernel.errors import PropertyError

    config, problems = load_config_partly(args.file)
    if config is None:
        return _config_errors(ConfigError(*problems))
    # Every problem of the file in one run: what did not parse, then what does not build.
    for problem in problems:
        print(f"psgateway: config error: {problem}", file=sys.stderr)
    bad = len(problems)

    async def build_all() -> None:
        nonlocal bad
        directory = Router().directory  # groups are built against an empty one: built, never started
        for entry in config.services:
            if entry.dials_in:
                # Its backend is made when the device greets, as under serve; its URL and secret
                # file were checked with the file.
                continue
            try:
                backend = open_backend(entry, directory)
            except PropertyError as exc:
                where = f"{config.source}: services ({entry.name})"
                print(f"psgateway: config error: {where}: {exc.message}", file=sys.stderr)
                bad += 1
                continue
            await backend.aclose()
        for device in config.devices:
            # Built here as the device process would build it, so a bad option shows now, not at start.
            try:
                build(device.type, device.options)
            except PropertyError as exc:
                where = f"{config.source}: devices ({device.name})"
                print(f"psgateway: config error: {where}: {exc.message}", file=sys.stderr)
                bad += 1

    asyncio.run(build_all())
    if bad:
        return EXIT_CONFIG
    counted = f"{len(config.services)} services"
    if config.devices:
        counted += f", {len(config.devices)} devices"
    listening = config.gateway.listen
    if config.http.listen:
        listening += f", HTTP on {config.http.listen}"
    if config.metrics.enabled and config.metrics.listen:
        listening += f", metrics on {config.metrics.listen}"
    print(f"{config.source}: fine ({counted}, listening on {listening})")
    if config.tls.client_ca and not config.tls.require_client_cert:
        from gateway.tls import OPTIONAL_CLIENT_CERT

        print(f"  note: {OPTIONAL_CLIENT_CERT}")
    # What a big registry meets first: one Listen follows a property of each registration, and the
    # registry's own entry is one of them (docs/registry-and-groups.md, "A big registry").
    most = config.limits.max_stream_properties
    print(
        f"  a Listen matches at most {most} properties (limits.max_stream_properties): one on "
        f"registry services.*.state follows at most {most - 1} services besides the registry; "
        "raise the limit for a bigger registry"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``psgateway``; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help", "--version")):
        # `psgateway` alone, or with only serve's options, serves.
        argv.insert(0, "serve")
    args = build_parser().parse_args(argv)
    try:
        code: int = args.func(args)
    except KeyboardInterrupt:
        return 130  # Ctrl-C before the command could take it over (128 + SIGINT)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
