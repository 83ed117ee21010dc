"""The C device library's example thermostat as a user meets it through the gateway, the same on
every board it runs on (simavr's ATmega328P, QEMU's Cortex-M): ``psctl`` runs kept as a
transcript, the ``history`` reading's checks, and a reset pressed in the middle of a Listen."""

from __future__ import annotations

import asyncio
import itertools
import struct
from collections.abc import Callable

import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from support.psctl import psctl

WAIT = 20.0


def run_psctl(address: str, transcript: list[str], *args: str) -> str:
    """``psctl ARGS...`` against ``address``, which must succeed; the command and its output are added
    to ``transcript``, and the output returned."""
    result = psctl(address, *args, timeout=WAIT)
    transcript += [f"$ psctl {' '.join(args)}", *result.stdout.rstrip("\n").split("\n")]
    assert result.returncode == 0, f"psctl {args}: {result.stdout}{result.stderr}"
    return result.stdout


def assert_history(reply: pb.GetResponse) -> None:
    """``history``: 8 readings of temp, int16 big-endian tenths of degC, one tick (0.1 degC) apart."""
    assert reply.HasField("data") and len(reply.data) == 16, reply
    readings = struct.unpack(">8h", reply.data)
    assert all(150 <= r <= 250 for r in readings), readings
    assert all(abs(a - b) <= 1 for a, b in itertools.pairwise(readings)), readings


async def assert_a_reset_mid_listen_is_a_gap(
    stub: pb_grpc.PropertyServiceStub, press_reset: Callable[[], None]
) -> None:
    """Press the board's reset while ``thermo``'s temp is being listened to: the firmware starts
    afresh and greets, the gateway LISTENs again and marks the next event as a gap, events flow
    after it, and the setpoint is back to 20; the binary ``history`` still reads right."""
    stream = stub.Listen(pb.ListenRequest(service="thermo", property="temp"))
    async with asyncio.timeout(WAIT):
        assert (await stream.read()).events
        await asyncio.to_thread(press_reset)
        while True:
            msg = await stream.read()
            assert msg is not grpc.aio.EOF
            if any(e.gap for e in msg.events):
                break
        assert (await stream.read()).events, "events flow after the reset"
    stream.cancel()
    reply = await stub.Get(pb.GetRequest(service="thermo", property="setpoint"), timeout=WAIT)
    assert reply.value == "20", "the reset set every value back"
    # The binary value (line protocol 1.2), base64 written by the device as it reads its ring.
    assert_history(await stub.Get(pb.GetRequest(service="thermo", property="history"), timeout=WAIT))
