"""Fixtures shared by every test folder (see tests/support/gateway_process.py, tests/support/etcd.py,
tests/support/walkthrough.py).

Hypothesis runs without its per-example deadline: these machines are shared, and a slow example
under load says nothing about the property being tested (speed lives in ``bench/``).
"""

from hypothesis import settings
from support.etcd import etcd, etcd_server
from support.gateway_process import demo_gateway, gateway_process
from support.walkthrough import fresh_demo_gateway

settings.register_profile("shared-machine", deadline=None)
settings.load_profile("shared-machine")

__all__ = ["demo_gateway", "etcd", "etcd_server", "fresh_demo_gateway", "gateway_process"]
