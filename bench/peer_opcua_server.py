"""The OPC UA server under test: an asyncua server with one writable String variable, ``bench/value``.

It is OPC UA's counterpart of the bare server: the variable holds the value,
a Read answers it, a Write sets it, and a subscription's monitored item on it
hears every change. No security (``None`` policy), as the gRPC servers under
test run in plaintext; the endpoint is on 127.0.0.1 only and no discovery
server is registered with.

Run ``python -m bench.peer_opcua_server --listen 127.0.0.1:0``; it prints
``listening on HOST:PORT`` to stderr, like the other servers under test, and
stops on SIGTERM, SIGINT or end of file on stdin. Starting takes a few
seconds: asyncua builds the standard address space first.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys

from bench.baseline import until_stopped
from bench.target import SERVICE, VALUE_PROPERTY

#: The namespace of the variable; a client looks its index up by this URI.
NAMESPACE = "urn:propertyservice:bench"
#: The variable's string identifier in that namespace.
VALUE_NODE = f"{SERVICE}/{VALUE_PROPERTY}"
#: The path of the endpoint URL.
ENDPOINT_PATH = "/bench/"


async def serve(listen: str) -> None:
    """Serve the variable on ``listen`` until stopped."""
    from asyncua import Server, ua

    server = Server()
    await server.init()
    host, port = listen.rsplit(":", 1)
    server.set_endpoint(f"opc.tcp://{host}:{port}{ENDPOINT_PATH}")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    index = await server.register_namespace(NAMESPACE)
    folder = await server.nodes.objects.add_object(index, SERVICE)
    variable = await folder.add_variable(
        ua.NodeId(VALUE_NODE, index), VALUE_PROPERTY, ua.Variant("0", ua.VariantType.String)
    )
    await variable.set_writable()
    async with server:
        assert server.bserver is not None
        print(f"listening on {server.bserver.hostname}:{server.bserver.port}", file=sys.stderr, flush=True)
        await until_stopped()


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.peer_opcua_server --listen HOST:PORT``."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.peer_opcua_server", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--listen", default="127.0.0.1:0", help="address to serve on (default %(default)s)")
    args = parser.parse_args(argv)
    # asyncua warns at every start that the None policy has no signing or encryption: it is meant so here.
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args.listen))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
