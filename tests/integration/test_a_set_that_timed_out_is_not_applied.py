"""A Set the client was told failed (DEADLINE_EXCEEDED) is not applied when the frozen device wakes:
the proxy sends ``#TAG CANCEL``, and the device drops the SET it finds cancelled."""

from __future__ import annotations

import asyncio
import os
import re
import signal

import grpc
import pytest
from line_device_support import device_process
from support.gateway_process import StartGateway

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 10.0
#: How long the device stays frozen after the client was told DEADLINE_EXCEEDED.
FROZEN_AFTER_S = 3.0


async def test_a_set_on_a_frozen_device_that_timed_out_is_not_applied_when_it_wakes(
    gateway_process: StartGateway,
) -> None:
    with device_process("--service", "sim-robot", "--name", "frozen", "--tcp", "127.0.0.1:0") as (
        proc,
        first,
    ):
        match = re.fullmatch(r"listening on (.+):(\d+)", first)
        assert match, first
        gw = gateway_process(f"""
            [gateway]
            call_timeout = 1.0
            [registry]
            period = 0
            [[services]]
            name = "frozen"
            url = "tcp://127.0.0.1:{match.group(2)}"
        """)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            before = await stub.Get(pb.GetRequest(service="frozen", property="speed"), timeout=WAIT)
            os.kill(proc.pid, signal.SIGSTOP)
            try:
                with pytest.raises(grpc.aio.AioRpcError) as info:
                    await stub.Set(
                        pb.SetRequest(service="frozen", property="speed", value="0.42"), timeout=WAIT
                    )
                assert info.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
                await asyncio.sleep(FROZEN_AFTER_S)
            finally:
                os.kill(proc.pid, signal.SIGCONT)
            await asyncio.sleep(0.5)
            after = await stub.Get(pb.GetRequest(service="frozen", property="speed"), timeout=WAIT)
            assert after.value == before.value != "0.42"
