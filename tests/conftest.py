"""Fixtures shared by every test folder (see tests/support/gateway_process.py)."""

from support.gateway_process import demo_gateway, gateway_process

__all__ = ["demo_gateway", "gateway_process"]
