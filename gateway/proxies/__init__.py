"""Proxies to line-protocol services (raw TCP, serial lines) and to other gateways.

:data:`gateway.backends.PROXY_SCHEMES` maps the ``tcp``, ``serial`` and ``grpc`` URL schemes
to their factories here.
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
