"""The Zenoh peer under test: one zenoh session in peer mode on loopback that holds ``bench/value``.

It is Zenoh's counterpart of the bare server: a subscriber on the key keeps
the latest value put to it, and a queryable answers a ``get`` of the key with
that value. The benchmark's sessions are zenoh *clients* connected to this
peer only, so every Get, put and delivered sample passes through this
process, as every call passes through a gRPC server (a peer routes between
the clients attached to it).

Nothing leaves the host: the peer listens on 127.0.0.1 only, and multicast
scouting (UDP to 224.0.0.224:7446, on by default) and gossip (peers telling
each other the addresses they know) are off, at both ends
(:func:`loopback_config`).

Run ``python -m bench.peer_zenoh_server --listen 127.0.0.1:0``; it prints
``listening on HOST:PORT`` to stderr, like the other servers under test, and
stops on SIGTERM, SIGINT or end of file on stdin.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
from collections.abc import Sequence
from typing import Any

from bench.baseline import until_stopped
from bench.target import SERVICE, VALUE_PROPERTY

#: The key of the one value, named like the gRPC servers' service and property.
KEY = f"{SERVICE}/{VALUE_PROPERTY}"
#: Zenoh's own answer time for a query, seconds (its default is 10 s); a Get that waits longer is an error.
QUERY_TIMEOUT = 10.0


def loopback_config(
    mode: str, *, listen: Sequence[str] = (), connect: Sequence[str] = (), adminspace: bool = False
) -> Any:
    """A zenoh configuration that talks only to the endpoints given: no scouting of any kind.

    ``mode`` is "peer" (the process under test) or "client" (the benchmark's
    sessions). The admin space lets the peer read back the port it was given.
    """
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    config.insert_json5("adminspace/enabled", json.dumps(adminspace))
    return config


def _locators(session: Any) -> list[str]:
    """The endpoints this session listens on, from its own admin space (``@/<zid>/peer``)."""
    for reply in session.get(f"@/{session.zid()}/peer", timeout=QUERY_TIMEOUT):
        if reply.ok is not None:
            found: list[str] = json.loads(bytes(reply.ok.payload.to_bytes()))["locators"]
            return found
    raise RuntimeError("the zenoh peer could not read its own locators")


def serve(listen: str) -> None:
    """Hold ``bench/value`` in a zenoh peer listening on ``listen`` until stopped."""
    import zenoh

    session = zenoh.open(loopback_config("peer", listen=[f"tcp/{listen}"], adminspace=True))
    value = ["0"]

    def on_put(sample: Any) -> None:
        value[0] = sample.payload.to_string()

    def on_get(query: Any) -> None:
        query.reply(KEY, value[0])

    try:
        subscriber = session.declare_subscriber(KEY, on_put)
        queryable = session.declare_queryable(KEY, on_get)
        tcp = [loc for loc in _locators(session) if loc.startswith("tcp/")]
        if not tcp:
            raise RuntimeError(f"the zenoh peer listens on no TCP endpoint: {_locators(session)}")
        print(f"listening on {tcp[0].removeprefix('tcp/')}", file=sys.stderr, flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(until_stopped())
        queryable.undeclare()
        subscriber.undeclare()
    finally:
        session.close()


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.peer_zenoh_server --listen HOST:PORT``."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.peer_zenoh_server", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--listen", default="127.0.0.1:0", help="address to serve on (default %(default)s)")
    args = parser.parse_args(argv)
    serve(args.listen)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
