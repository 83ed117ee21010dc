"""The demo's devices (rover1 on raw TCP, rover2 on a pty serial line) through a real gateway process,
the device processes' lifecycle, and a gRPC Listen that survives a device reconnect."""

from __future__ import annotations

import asyncio
import os
import re
import signal

import grpc
import psutil
import pytest
from line_device_support import device_process
from support.gateway_process import GatewayProcess, StartGateway
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 15.0
ROVERS = ("rover1", "rover2")
STARTED = re.compile(r"device (\S+) started \(pid (\d+)\) at (\S+)")


def device_pids(gw: GatewayProcess) -> dict[str, int]:
    """The PIDs of the device processes, from the gateway's log."""
    return {m.group(1): int(m.group(2)) for m in STARTED.finditer(gw.output)}


def xy(value: str) -> tuple[float, float]:
    x, y = (float(t) for t in value.strip("()").split()[:2])
    return x, y


async def get(stub: pb_grpc.PropertyServiceStub, service: str, prop: str) -> str:
    reply = await stub.Get(pb.GetRequest(service=service, property=prop), timeout=WAIT)
    return str(reply.value)


async def test_registry_lists_the_devices_with_their_urls(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        rover1 = await get(stub, "registry", "services.rover1.url")
        rover2 = await get(stub, "registry", "services.rover2.url")
    assert re.fullmatch(r"tcp://127\.0\.0\.1:\d+", rover1)
    # A serial device is reached through a link to its pseudo-terminal, pointed anew when it restarts.
    match = re.fullmatch(r"serial://(/\S+/tty)\?baudrate=115200", rover2)
    assert match and re.fullmatch(r"/dev/pts/\d+", os.readlink(match.group(1))), rover2
    # Each URL is logged with the device's start, and each device is a process of its own.
    pids = device_pids(demo_gateway)
    assert set(pids) == set(ROVERS)
    assert f"at {rover1}" in demo_gateway.output and f"at {rover2}" in demo_gateway.output
    for pid in pids.values():
        assert pid != demo_gateway.proc.pid
        assert psutil.Process(pid).ppid() == demo_gateway.proc.pid


@pytest.mark.parametrize(("rover", "start"), [("rover1", 3.0), ("rover2", 4.0)])
async def test_get_set_listen_on_a_device(demo_gateway: GatewayProcess, rover: str, start: float) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        assert await get(stub, rover, "location") == f"({start:g} 0 0 0 0 0)"
        assert "behaviors.moveto" in (await get(stub, rover, "properties")).strip("()").split()
        await stub.Set(pb.SetRequest(service=rover, property="speed", value="2"), timeout=WAIT)
        call = stub.Listen(pb.ListenRequest(service=rover, property="location"))
        target = (start + 1, 1.0)
        async with asyncio.timeout(WAIT):
            first = await call.read()
            assert [e.value for e in first.events] == [f"({start:g} 0 0 0 0 0)"]
            assert (await call.read()).sync
            moveto = f"<marker><location>({start + 1:g} 1)</location></marker>"
            await stub.Set(pb.SetRequest(service=rover, property="behaviors.moveto", value=moveto))
            values: list[str] = []
            while not values or xy(values[-1]) != target:
                msg = await call.read()
                assert all(e.service == rover and e.property == "location" for e in msg.events)
                values += [e.value for e in msg.events]
        call.cancel()
        assert len(values) >= 2, "the robot drove there, event by event"
        assert xy(await get(stub, rover, "location")) == target
        assert all(start <= xy(v)[0] <= start + 1 for v in values)
        # Errors from the device come back with their own codes.
        with pytest.raises(grpc.aio.AioRpcError) as info:
            await stub.Get(pb.GetRequest(service=rover, property="nosuch"), timeout=WAIT)
        assert info.value.code() == grpc.StatusCode.NOT_FOUND


DEVICES_CONFIG = """
[gateway]
log_level = "info"

[[devices]]
name = "wifi1"
type = "sim-sensor"
tcp = "127.0.0.1:0"

[[devices]]
name = "uart1"
type = "sim-robot"
serial = "pty"
baudrate = 9600
options = { start = [5.0, 5.0] }
"""


def gone(pid: int, wait_s: float) -> bool:
    """True when process ``pid`` has ended (and was reaped) within ``wait_s`` seconds."""
    try:
        psutil.Process(pid).wait(wait_s)
    except psutil.NoSuchProcess:
        return True
    except psutil.TimeoutExpired:
        return False
    return True


async def test_device_processes_end_with_the_gateway(gateway_process: StartGateway) -> None:
    gw = gateway_process(DEVICES_CONFIG)
    pids = device_pids(gw)
    assert set(pids) == {"wifi1", "uart1"}
    assert "serial:///dev/pts/" in gw.output and "?baudrate=9600" in gw.output
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        assert await get(stub, "uart1", "location") == "(5 5 0 0 0 0)"
        assert float(await get(stub, "wifi1", "data")) > -100
    assert all(psutil.pid_exists(pid) for pid in pids.values())
    assert gw.stop() == 0
    assert all(gone(pid, 5) for pid in pids.values())
    assert "device uart1 stopped" in gw.output


async def test_device_processes_end_when_the_gateway_is_killed(gateway_process: StartGateway) -> None:
    gw = gateway_process(DEVICES_CONFIG)
    pids = device_pids(gw)
    os.kill(gw.proc.pid, signal.SIGKILL)
    gw.proc.wait(5)
    # Nobody ends them by PID now: they notice that their stdin pipe from the gateway closed.
    assert all(gone(pid, 10) for pid in pids.values())


async def test_a_bad_device_entry_stops_the_gateway_with_a_clear_message(
    gateway_process: StartGateway,
) -> None:
    bad = '[[devices]]\nname = "r"\ntype = "sim-robot"\ntcp = "127.0.0.1:0"\noptions = { wheels = 3 }\n'
    with pytest.raises(RuntimeError, match="bad options for 'sim-robot'"):
        gateway_process(bad)


async def test_a_listen_stream_survives_a_device_reconnect(gateway_process: StartGateway) -> None:
    with device_process("--service", "sim-robot", "--name", "bot", "--tcp", "127.0.0.1:0") as (proc, first):
        port = int(first.rpartition(":")[2])
        gw = gateway_process(f"""
            [[services]]
            name = "bot"
            url = "tcp://127.0.0.1:{port}"
            options = {{ timeout = 2.0, backoff_initial = 0.05, backoff_max = 0.3 }}
        """)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            call = stub.Listen(pb.ListenRequest(service="bot", property="speed"))
            async with asyncio.timeout(WAIT):
                assert [e.value for e in (await call.read()).events] == ["0.5"]
                assert (await call.read()).sync
                await stub.Set(pb.SetRequest(service="bot", property="speed", value="0.8"))
                changed = (await call.read()).events
                assert [(e.value, e.gap) for e in changed] == [("0.8", False)]

                os.kill(proc.pid, signal.SIGKILL)  # the device dies: power cut, no goodbye
                proc.wait(5)
                with device_process(
                    "--service", "sim-robot", "--name", "bot", "--tcp", f"127.0.0.1:{port}"
                ) as (again, _):
                    # The same stream goes on: the new device's current value, marked as a gap.
                    events = (await call.read()).events
                    assert [(e.value, e.gap) for e in events] == [("0.5", True)]
                    assert events[0].sequence == changed[-1].sequence + 1
                    await stub.Set(pb.SetRequest(service="bot", property="speed", value="0.9"))
                    after = (await call.read()).events
                    assert [(e.value, e.gap) for e in after] == [("0.9", False)]
                    assert again.poll() is None
            call.cancel()


RESTARTED = re.compile(r"device (\S+): started again \(pid (\d+), restart (\d+)\)")


@pytest.mark.parametrize(("rover", "where"), [("wifi1", "data"), ("uart1", "location")])
async def test_a_device_process_that_dies_is_started_again(
    gateway_process: StartGateway, rover: str, where: str
) -> None:
    gw = gateway_process(DEVICES_CONFIG)
    pid = device_pids(gw)[rover]
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await get(stub, rover, where)
        os.kill(pid, signal.SIGKILL)  # the device dies: no goodbye
        assert gone(pid, 5)
        # The gateway starts it again; the proxy reconnects; the registry says up; a Get answers.
        await eventually(
            lambda: asyncio.sleep(0, gw.output), lambda out: bool(RESTARTED.search(out)), within=WAIT
        )

        async def state_and_value() -> tuple[str, str]:
            return await get(stub, "registry", f"services.{rover}.state"), await get(stub, rover, where)

        _, value = await eventually(
            state_and_value, lambda got: got[0] == "up", within=WAIT, retry_on=(grpc.aio.AioRpcError,)
        )
        assert value
        restarted = {m.group(1): int(m.group(2)) for m in RESTARTED.finditer(gw.output)}
        assert restarted[rover] != pid
        assert psutil.Process(restarted[rover]).ppid() == gw.proc.pid
        assert f"device {rover}: its process {pid} ended" in gw.output
    # The restarted process ends with the gateway too.
    assert gw.stop() == 0
    assert gone(restarted[rover], 5)
