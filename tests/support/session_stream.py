"""Reading the replies of a gRPC Session stream in a test, bounded."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from support.waiting import WAIT


async def replies_until(
    call: Any, done: Callable[[list[pb.Reply]], bool], within: float = WAIT
) -> list[pb.Reply]:
    """Read replies until ``done(all_replies_so_far)`` is true; fail if the stream ends or time runs out."""
    out: list[pb.Reply] = []
    try:
        async with asyncio.timeout(within):
            while not done(out):
                msg = await call.read()
                assert msg is not grpc.aio.EOF, f"stream ended early after {out[-5:]}"
                out.extend(msg.replies)
    except TimeoutError:
        raise AssertionError(
            f"the awaited replies did not come within {within} s; last: {out[-5:]}"
        ) from None
    return out
