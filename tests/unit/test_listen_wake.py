"""The one-waiter wake-up of a Listen writer: a wake is never lost, and never served twice."""

from __future__ import annotations

import asyncio

from gateway.engine.listen.drain import Wake


async def test_a_wake_before_the_writer_asks_lets_it_go_on_at_once_then_makes_it_wait() -> None:
    wake = Wake()
    wake.set()
    wake.set()
    assert wake.waiter() is None
    waiter = wake.waiter()
    assert waiter is not None and not waiter.done()


async def test_a_wake_while_the_writer_waits_completes_its_waiter_and_is_spent() -> None:
    wake = Wake()
    waiter = wake.waiter()
    assert waiter is not None
    wake.set()
    assert waiter.done()
    await waiter
    assert wake.waiter() is not None  # nothing new: the writer waits again


async def test_a_wake_after_the_waiting_writer_was_cancelled_is_kept_for_its_next_round() -> None:
    wake = Wake()
    waiting = asyncio.ensure_future(wake.wait())
    await asyncio.sleep(0)
    waiting.cancel()
    await asyncio.gather(waiting, return_exceptions=True)
    wake.set()
    assert wake.waiter() is None


async def test_wait_returns_once_set() -> None:
    wake = Wake()
    waiting = asyncio.ensure_future(wake.wait())
    await asyncio.sleep(0)
    assert not waiting.done()
    wake.set()
    await asyncio.wait_for(waiting, 5)
    wake.set()
    await asyncio.wait_for(wake.wait(), 5)  # set before: at once
