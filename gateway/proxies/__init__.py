"""Proxies to line-protocol services (raw TCP, serial lines) and to other gateways; the line listener.

Importing this package registers the ``tcp``, ``serial`` and ``grpc`` URL schemes in
:data:`gateway.backends.PROXY_SCHEMES` and the raw-TCP line listener in
:data:`gateway.backends.LINE_LISTENER`.
"""

from __future__ import annotations

from gateway.proxies.grpc_proxy import GrpcProxy, GrpcProxyOptions, open_grpc_backend
from gateway.proxies.line_proxy import LineProxy, ProxyOptions
from gateway.proxies.serial import SerialProxy, open_serial_backend
from gateway.proxies.tcp import TcpProxy, open_tcp_backend

__all__ = [
    "GrpcProxy",
    "GrpcProxyOptions",
    "LineProxy",
    "ProxyOptions",
    "SerialProxy",
    "TcpProxy",
    "open_grpc_backend",
    "open_serial_backend",
    "open_tcp_backend",
]


def _register() -> None:
    try:
        from gateway import backends
    except ImportError:  # the gateway's backend table is not there: the proxies still work on their own
        return
    backends.PROXY_SCHEMES.setdefault("tcp", open_tcp_backend)
    backends.PROXY_SCHEMES.setdefault("serial", open_serial_backend)
    backends.PROXY_SCHEMES.setdefault("grpc", open_grpc_backend)
    if backends.LINE_LISTENER is None:
        from gateway.line_listener import start_line_listener

        backends.LINE_LISTENER = start_line_listener


_register()
