"""Every way of calling a gateway that cannot be reached raises GatewayUnreachable, as docs/client.md says."""

from __future__ import annotations

import pytest
from support.ports import free_port

from clients import AsyncClient, Client, GatewayUnreachable


def closed_target() -> str:
    """host:port of a loopback port nobody listens on (bound, then released)."""
    return f"127.0.0.1:{free_port()}"


async def test_async_calls_and_session_calls_are_gateway_unreachable() -> None:
    async with AsyncClient(closed_target(), timeout=5) as c:
        with pytest.raises(GatewayUnreachable):
            await c.get("scout1", "location")
        async with c.session() as s:
            with pytest.raises(GatewayUnreachable) as failed:
                await s.get("scout1", "location")
            assert "cannot reach the gateway" in str(failed.value)
            with pytest.raises(GatewayUnreachable):
                await s.set("scout1", "speed", 1)
            with pytest.raises(GatewayUnreachable):
                await anext(s.listen("scout1", "location"))
        async with c.session() as s:
            # A listen started before the session learns that the gateway is unreachable.
            with pytest.raises(GatewayUnreachable):
                await anext(s.listen("scout1", "location"))
        with pytest.raises(GatewayUnreachable):
            await anext(c.listen("scout1", "location"))


def test_sync_session_call_is_gateway_unreachable() -> None:
    with Client(closed_target(), timeout=5) as c, c.session() as s, pytest.raises(GatewayUnreachable):
        s.get("scout1", "location")


def test_every_fresh_sync_session_reports_gateway_unreachable() -> None:
    # The writer may find the call finished before the reader has seen why; the reason must still win.
    with Client(closed_target(), timeout=5) as c:
        for _ in range(20):
            with c.session() as s, pytest.raises(GatewayUnreachable):
                s.get("scout1", "location")
