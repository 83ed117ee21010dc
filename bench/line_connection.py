"""Instructions per request through a line-protocol connection: the proxy's own hot path.

``python -m bench.line_connection`` runs one process under ``valgrind --tool=callgrind`` twice,
making N and then 4·N Gets through :class:`gateway.proxies.connection.LineConnection` (the
connection of the TCP and serial proxies) on an in-memory stream: a GET line out, its OK read
back, its future resolved. The difference of the two counts over 3·N is what one request costs
the connection, with the interpreter's start-up and the imports taken out. No socket, no gRPC:
the part of a proxied Get that the line proxy itself adds (the rest is measured by
``python -m bench.instructions`` and part (e) of ``python -m bench``). ``--calls N`` (default
1000). ``PYTHONHASHSEED`` is fixed for both runs, so that they hash alike.

Needs valgrind (``apt-get install valgrind``); without it the command says so and exits 2.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.servers import ROOT


class _Sink:
    """The stream's write end: keeps what the connection writes, for the loop to answer."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.written.append(data)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


async def cycles(calls: int) -> None:
    """``calls`` Gets, one at a time, answered as a device would."""
    from gateway.proxies.connection import LineConnection
    from services.kernel.line_protocol import Get

    connection = LineConnection(label="bench", on_event=lambda frame: None)
    sink = _Sink()
    connection.connection_made(sink)  # type: ignore[arg-type]
    connection.data_received(b"HELLO 1 name=bench type=bench push=1\n")
    await connection.hello
    request = Get("speed", {})
    for _ in range(calls):
        reply = connection.start_request(request, 5.0)
        assert reply is not None
        connection._flush()  # the end of the loop turn, where the line goes out
        tag = sink.written.pop().split(b" ", 1)[0]
        connection.data_received(tag + b" OK 1.5\n")
        await reply


def _counted(calls: int, folder: Path) -> int:
    out = folder / f"callgrind.{calls}"
    env = dict(os.environ, PYTHONHASHSEED="0")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
    run = subprocess.run(
        [
            "valgrind",
            "--tool=callgrind",
            f"--callgrind-out-file={out}",
            sys.executable,
            "-m",
            "bench.line_connection",
            "--run",
            str(calls),
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        check=True,
    )
    found = re.search(r"Collected : (\d+)", run.stderr)
    if found is None:
        raise RuntimeError(f"no count from callgrind:\n{run.stderr[-2000:]}")
    return int(found.group(1))


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.line_connection``."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.line_connection", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--calls", type=int, default=1000, help="N: the runs make N and 4·N Gets")
    parser.add_argument("--run", type=int, help=argparse.SUPPRESS)  # the measured process itself
    args = parser.parse_args(argv)
    if args.run is not None:
        asyncio.run(cycles(args.run))
        return 0
    if shutil.which("valgrind") is None:
        print("needs valgrind (apt-get install valgrind)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as folder:
        few, many = (_counted(n, Path(folder)) for n in (args.calls, 4 * args.calls))
    per = (many - few) / (3 * args.calls)
    print(f"line connection: {per:,.0f} instructions per Get (GET out, OK in, future resolved)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
