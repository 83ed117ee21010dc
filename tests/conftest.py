"""Fixtures shared by every test folder (see tests/support/gateway_process.py, tests/support/etcd.py).

Hypothesis runs without its per-example deadline: these machines are shared, and a slow example
under load says nothing about the property being tested (speed lives in ``bench/``).
"""

from hypothesis import settings
from support.etcd import etcd, etcd_server
from support.gateway_process import demo_gateway, gateway_process

settings.register_profile("shared-machine", deadline=None)
settings.load_profile("shared-machine")

__all__ = ["demo_gateway", "etcd", "etcd_server", "gateway_process"]
