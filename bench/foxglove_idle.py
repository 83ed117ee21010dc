"""What an idle Foxglove client costs the gateway: ``python -m bench.foxglove_idle``.

A gateway process serves a config (one simulated robot, or the demo with ``--demo``: 316
channels); this process opens ``--connections`` Foxglove WebSocket connections
(``foxglove.websocket.v1``), reads each one's server info and advertisements, and leaves them
idle. The gateway's RSS before and after, divided by the connections, is one idle connection's
cost: its socket, its request, and its catalog (the schema texts and property models are shared
by every connection; the channel tables are its own). Figures in docs/ros-and-foxglove.md.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
from pathlib import Path

import aiohttp

from bench.servers import ROOT, ServerProcess
from bench.sse import http_url

ROBOT = '[[services]]\nname = "bot"\ntype = "sim-robot"\n'
#: Connections one address may hold for the run (the front end's default is 64 a client).
PLACES = "\n[http]\nmax_streams_per_client = 10000\n"
#: Connections opened (and measured as the gateway's working set) before the count starts.
WARM_UP = 5


async def measure(config: str, connections: int) -> tuple[float, int, int]:
    """KiB per idle connection, and the gateway's RSS before and after, in bytes."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "gateway.toml"
        path.write_text(config)
        argv = [
            "gateway.cli",
            "serve",
            "--config",
            str(path),
            "--listen",
            "127.0.0.1:0",
            "--http",
            "127.0.0.1:0",
        ]
        server = await ServerProcess.start("gateway", argv)
        try:
            url = http_url(server) + "foxglove"
            async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as session:
                opened: list[aiohttp.ClientWebSocketResponse] = []

                async def one() -> None:
                    ws = await session.ws_connect(url, protocols=["foxglove.websocket.v1"])
                    opened.append(ws)
                    for _ in range(3):  # serverInfo, advertise, advertiseServices
                        await ws.receive()

                for _ in range(WARM_UP):
                    await one()
                await asyncio.sleep(1.0)
                before = server.rss_bytes()
                for _ in range(connections):
                    await one()
                await asyncio.sleep(1.0)
                after = server.rss_bytes()
                for ws in opened:
                    await ws.close()
        finally:
            await server.stop()
    return (after - before) / connections / 1024, before, after


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.foxglove_idle", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--connections", type=int, default=200, help="idle connections to open (default 200)")
    parser.add_argument(
        "--demo", action="store_true", help="serve the demo (gateway/demo.toml) instead of one robot"
    )
    args = parser.parse_args(argv)
    if args.demo:
        demo = (ROOT / "gateway" / "demo.toml").read_text()
        # The demo's HTTP section gains the places; its storage folder goes to a temporary one.
        config = demo.replace(
            'listen = "127.0.0.1:8080"\n', 'listen = "127.0.0.1:8080"\nmax_streams_per_client = 10000\n', 1
        )
        config = config.replace('directory = "./.demo-files"', f'directory = "{tempfile.mkdtemp()}"')
    else:
        config = ROBOT + PLACES
    per, before, after = asyncio.run(measure(config, args.connections))
    what = "the demo" if args.demo else "one robot"
    print(
        f"{what}: {args.connections} idle Foxglove connections: {per:.1f} KiB each"
        f" (gateway RSS {before / 1e6:.1f} -> {after / 1e6:.1f} MB)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
