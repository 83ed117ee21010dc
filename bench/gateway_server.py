"""The gateway under test: a real :class:`gateway.app.Gateway` serving one bench-only service.

The service is :class:`BenchTarget`, a plain Resource with settable text
properties, served in-process by ``services.kernel.core.LocalService`` — the same
path as every Python service behind the gateway (router, listen hub, Session
handler, class wrapper), with nothing device-like behind it.

Run ``python -m bench.gateway_server --listen 127.0.0.1:0``; it prints
``listening on HOST:PORT`` to stderr, like ``psgateway serve``, and stops on
SIGTERM, SIGINT or end of file on stdin.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys

from bench.baseline import until_stopped
from bench.target import SERVICE
from services.kernel.core import Resource


class BenchTarget(Resource):
    """The property under test: settable text, plus ten more for the batched Listen part."""

    resource_type = "bench"

    value: str = "0"
    v0: str = "0"
    v1: str = "0"
    v2: str = "0"
    v3: str = "0"
    v4: str = "0"
    v5: str = "0"
    v6: str = "0"
    v7: str = "0"
    v8: str = "0"
    v9: str = "0"


async def serve(
    listen: str, config_file: str | None = None, http: str = "", metrics: str | None = ""
) -> None:
    """Run a gateway with :class:`BenchTarget` as service ``bench`` until stopped.

    ``config_file`` adds security sections (``[tls]``, ``[auth]``, ``[[rules]]``) to measure their cost;
    ``http`` (HOST:PORT) turns the HTTP front end on, printed as ``HTTP front end and console on URL``;
    ``metrics`` (HOST:PORT) serves ``/metrics`` there, printed as ``metrics on URL``; None turns the
    metrics off (nothing counted), "" leaves them as the config says (on by default).
    """
    from dataclasses import replace

    from gateway.app import Gateway
    from gateway.config import Config, GatewaySection, HttpSection, MetricsSection, load_config
    from services.kernel.core import LocalService

    config = Config(gateway=GatewaySection(listen=listen, log_level="warning"))
    if config_file:
        loaded = load_config(config_file)
        config = replace(loaded, gateway=replace(loaded.gateway, listen=listen, log_level="warning"))
    if http:
        config = replace(config, http=HttpSection(listen=http, console=False))
    if metrics is None:
        config = replace(config, metrics=MetricsSection(enabled=False))
    elif metrics:
        config = replace(config, metrics=MetricsSection(listen=metrics))
    gateway = Gateway(config, backends={SERVICE: LocalService(BenchTarget())})
    await gateway.start()
    if gateway.http is not None:
        print(f"HTTP front end and console on {gateway.http.url}", file=sys.stderr, flush=True)
    if gateway.metrics_address:
        print(f"metrics on http://{gateway.metrics_address}/metrics", file=sys.stderr, flush=True)
    print(f"listening on {gateway.address}", file=sys.stderr, flush=True)
    try:
        await until_stopped()
    finally:
        await gateway.stop()


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.gateway_server --listen HOST:PORT``."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.gateway_server", description="The gateway under test, serving service 'bench'."
    )
    parser.add_argument("--listen", default="127.0.0.1:0", help="address to serve on (default %(default)s)")
    parser.add_argument("--config", metavar="FILE", help="a config whose [tls], [auth] and [[rules]] apply")
    parser.add_argument("--http", default="", metavar="HOST:PORT", help="serve the HTTP front end there too")
    metrics = parser.add_mutually_exclusive_group()
    metrics.add_argument("--metrics", default="", metavar="HOST:PORT", help="serve /metrics there too")
    metrics.add_argument(
        "--no-metrics",
        action="store_true",
        help="metrics off: no call is counted ([metrics] enabled = false)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s"
    )
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args.listen, args.config, args.http, None if args.no_metrics else args.metrics))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
