"""Fixtures shared by every test folder (see tests/support/gateway_process.py, tests/support/etcd.py)."""

from support.etcd import etcd, etcd_server
from support.gateway_process import demo_gateway, gateway_process

__all__ = ["demo_gateway", "etcd", "etcd_server", "gateway_process"]
