"""Bursts of unary calls through one AsyncClient against a real demo gateway process."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from clients import AsyncClient, DeadlineExceeded

BURST = 3000


@pytest.fixture(scope="module")
def demo_target(demo_gateway: Any) -> str:
    """Address of this module's demo gateway process (see conftest.py)."""
    return str(demo_gateway.address)


async def test_a_burst_of_concurrent_gets_all_succeed(demo_target: str) -> None:
    # Unbounded, grpc.aio answers some calls of such a burst on one channel with CANCELLED.
    async with AsyncClient(demo_target, timeout=60.0) as c:
        results = await asyncio.gather(
            *(c.get("scout2", "location.x") for _ in range(BURST)), return_exceptions=True
        )
    failures = [r for r in results if isinstance(r, BaseException)]
    assert failures == [], f"{len(failures)} of {BURST} failed, e.g. {failures[0]!r}"
    assert all(isinstance(r, str) and r for r in results)


async def test_a_caller_waiting_for_a_call_slot_is_bounded_by_its_timeout() -> None:
    # A listener that accepts connections and never answers keeps the one slot busy.
    accepted: list[asyncio.StreamWriter] = []
    server = await asyncio.start_server(lambda r, w: accepted.append(w), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with AsyncClient(f"127.0.0.1:{port}", timeout=30.0, max_in_flight=1) as c:
            busy = asyncio.create_task(c.get("scout1", "location"))
            await asyncio.sleep(0.1)
            assert not busy.done()
            c.timeout = 0.3
            with pytest.raises(DeadlineExceeded) as caught:
                await c.get("scout1", "location.x")
            assert "max_in_flight" in str(caught.value)
            assert caught.value.property == "location.x"
            assert not busy.done()
            busy.cancel()
            with pytest.raises(asyncio.CancelledError):
                await busy
    finally:
        server.close()
        # Since Python 3.12 wait_closed also waits for the accepted connections: close them.
        for writer in accepted:
            writer.close()
        await server.wait_closed()


@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_max_in_flight_must_be_a_positive_whole_number(bad: Any) -> None:
    with pytest.raises(ValueError, match="max_in_flight"):
        AsyncClient("127.0.0.1:1", max_in_flight=bad)
