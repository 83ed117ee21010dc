"""The example device's ATmega328P firmware, run in simavr with USART0 on a host pty, driven by a real
gateway's serial proxy: Get, Set, Listen, a reset, and a 64-byte receive ring that loses nothing
because the gateway keeps to the device's flow control (inflight=1 rxbuf=64)."""

from __future__ import annotations

import asyncio
import os
import re
import select
import signal
import subprocess
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from support.c_device import CProgram, build
from support.gateway_process import StartGateway
from support.serial_tap import WireTap
from support.thermostat import assert_a_reset_mid_listen_is_a_gap, run_psctl
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 20.0
RXBUF = 64
ATMEGA328P_SRAM = 2048
RAM_BUDGET = 1024
# A keep-alive PING every second: under inflight=1 it queues behind requests like any other.
OPTIONS = "{ timeout = 5.0, backoff_initial = 0.05, backoff_max = 0.5, keepalive = 1.0 }"


@pytest.fixture(scope="module")
def firmware(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the simavr harness, the firmware ELF)."""
    into = tmp_path_factory.mktemp("avr-build")
    build("avr", into)
    build("sim", into)
    return into / "sim" / "simavr_uart", into / "avr" / "thermostat.elf"


@pytest.fixture
def mcu(firmware: tuple[Path, Path]) -> Iterator[CProgram]:
    harness, elf = firmware
    with CProgram([str(harness), str(elf)]) as program:
        yield program


def read_for(fd: int, seconds: float) -> str:
    """Everything the device sends within ``seconds``."""
    out = b""
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        if select.select([fd], [], [], left)[0]:
            out += os.read(fd, 4096)
    return out.decode()


def test_the_harness_ends_on_sigterm(firmware: tuple[Path, Path], tmp_path: Path) -> None:
    """SIGTERM ends the run at once, its output going to a file as when started in the background:
    the SRAM figure printed, exit code 0. A few runs: stopping simavr's pty thread could hang."""
    harness, elf = firmware
    for run in range(5):
        log = tmp_path / f"simavr{run}.log"
        with log.open("w") as out:
            proc = subprocess.Popen(
                [str(harness), str(elf)], stdin=subprocess.DEVNULL, stdout=out, stderr=out
            )
        try:
            deadline = time.monotonic() + WAIT
            while "serial port" not in log.read_text() and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.1 * run)
            proc.terminate()
            try:
                code = proc.wait(3.0)
            except subprocess.TimeoutExpired:
                code = None
            assert code == 0, f"run {run}: {log.read_text()}"
            assert "untouched SRAM:" in log.read_text()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)


def test_the_ring_overflows_without_flow_control_and_says_so(mcu: CProgram) -> None:
    """The control experiment: requests pipelined past 64 bytes while the device is still sending a
    long reply overflow its ring; the device answers the damaged line ERR 15 instead of merging it."""
    fd = os.open(mcu.where, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        assert "HELLO 1 name=thermo1" in (os.write(fd, b"HELLO\n"), read_for(fd, 1.0))[1]
        burst = b"GET properties.model\n" + b"".join(b"#%d GET setpoint\n" % n for n in range(1, 6))
        os.write(fd, burst)
        answer = read_for(fd, 1.5)
        assert "#1 OK 20" in answer and "#5 OK 20" not in answer, answer
        # The LF of the damaged line was among the bytes lost: the next LF ends it, and the device
        # answers it ERR 15 (untagged: the tag may be what was lost), never a merged request.
        os.write(fd, b"\n")
        answer += read_for(fd, 1.0)
        assert "ERR 15 bytes lost" in answer and "#5 OK" not in answer, answer
        os.write(fd, b"#9 GET setpoint\n")
        assert "#9 OK 20" in read_for(fd, 1.0), "the next line is read afresh"
    finally:
        os.close(fd)


async def test_the_firmware_in_simavr_through_the_gateway(
    gateway_process: StartGateway, mcu: CProgram, capsys: pytest.CaptureFixture[str]
) -> None:
    with WireTap(mcu.where) as tap:
        gw = gateway_process(
            f'[[services]]\nname = "thermo"\nurl = "serial://{tap.path}?baudrate=115200"\n'
            f"options = {OPTIONS}\n"
        )
        shown: list[str] = []
        run = lambda *args: asyncio.to_thread(run_psctl, gw.address, shown, *args)  # noqa: E731
        assert "temp" in await run("get", "thermo", "properties")
        # Five paths in one Get: the gateway would send them all at once; the device takes one.
        five = await run("get", "thermo", "temp", "setpoint", "location", "label", "temp.gui")
        assert "setpoint = 20\n" in five and "label = bench" in five and "temp.gui = gauge" in five, five
        assert "23.5" in await run("set", "thermo", "setpoint", "23.5")
        assert "shelf 2" in await run("set", "thermo", "label", "shelf 2")
        # A whole pose: 39 bytes on the line under an 8-digit tag, within what the ring holds.
        assert "(10.25 20.5 0 0 0 0)" in await run("set", "thermo", "location", "(10.25 20.5 0 0 0 0)")
        events = await run("listen", "thermo", "temp", "--count", "3")
        assert len(re.findall(r"temp", events)) >= 3, events
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            for _ in range(3):  # three-property Listens, each at once
                stream = stub.Listen(
                    pb.ListenRequest(
                        service="thermo",
                        property="temp",
                        more=[pb.PropertyRef(property="setpoint"), pb.PropertyRef(property="label")],
                    )
                )
                seen: dict[str, str] = {}
                async with asyncio.timeout(WAIT):
                    while len(seen) < 3:
                        msg = await stream.read()
                        assert msg is not grpc.aio.EOF
                        seen.update({e.property: e.value for e in msg.events})
                assert seen["setpoint"] == "23.5" and seen["label"] == "shelf 2"
                stream.cancel()
            # A reset mid-session (SIGUSR1 to the harness: avr_reset).
            await assert_a_reset_mid_listen_is_a_gap(stub, mcu.reset)
        transcript = tap.transcript()
        # The 64-byte ring never overflowed: no line was damaged, and the gateway never had more
        # request bytes on the wire than the device said it can hold.
        assert "ERR 15" not in transcript, transcript
        assert "inflight=1 rxbuf=64" in transcript
        assert re.search(r"^< #\w+ PONG", transcript, re.M), "the device answered the gateway's keep-alive"
        assert 0 < tap.most_unanswered_bytes() <= RXBUF, transcript
    mcu.stop()
    untouched = re.search(r"untouched SRAM: (\d+) bytes", mcu.output)
    assert untouched, mcu.output
    used = ATMEGA328P_SRAM - int(untouched.group(1))
    assert used <= RAM_BUDGET
    with capsys.disabled():
        print("\n--- psctl against the gateway, the firmware in simavr ---")
        print("\n".join(shown))
        print(f"--- the serial line (> gateway, < device), {len(tap.record())} lines; RAM used: {used} B")
        print("\n".join(transcript.split("\n")[:40]))


async def test_an_overrun_on_the_serial_line_costs_one_resend_not_a_timeout(
    gateway_process: StartGateway, mcu: CProgram
) -> None:
    """Eight ``GET properties.model`` at once and a Listen, with line noise that overruns the 64-byte
    ring while the device sends its longest reply: the device answers the damaged line with an
    untagged ``ERR 15``, the gateway sends the lost request again at once, and every call is
    answered well within the 5 s timeout."""
    with WireTap(mcu.where) as tap:
        gw = gateway_process(
            f'[[services]]\nname = "thermo"\nurl = "serial://{tap.path}?baudrate=115200"\n'
            f"options = {OPTIONS}\n"
        )
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            # The gateway may be up before it has opened the pty (a loaded machine): ask until it has.
            setpoint = pb.GetRequest(service="thermo", property="setpoint")
            await eventually(lambda: stub.Get(setpoint, timeout=WAIT), retry_on=(grpc.aio.AioRpcError,))
            # 80 bytes arrive while the firmware writes the model (about 400 bytes): more than its
            # ring holds, so the next line it reads, the gateway's next request, lost bytes.
            tap.add_noise(b"GET properties.model", b"~" * 80)
            began = time.monotonic()
            model = pb.GetRequest(service="thermo", property="properties.model")
            gets = [stub.Get(model, timeout=WAIT) for _ in range(8)]
            stream = stub.Listen(pb.ListenRequest(service="thermo", property="temp"))
            replies = await asyncio.gather(*gets)
            async with asyncio.timeout(WAIT):
                first = await stream.read()
            took = time.monotonic() - began
            stream.cancel()
        assert all("setpoint" in reply.value for reply in replies)
        assert first is not grpc.aio.EOF and first.events[0].property == "temp"
        assert took < 2.5, f"{took:.1f} s: a lost request waited for its timeout"
        record = tap.record()
        lost = [i for i, (who, line) in enumerate(record) if who == "dev" and line.startswith("ERR 15")]
        assert lost, tap.transcript()
        # The request before the ERR 15 went out again, the same line, and was answered.
        resent = next(line for who, line in reversed(record[: lost[0]]) if who == "gw")
        assert next(line for who, line in record[lost[0] + 1 :] if who == "gw") == resent, tap.transcript()
    assert "never retrieved" not in gw.output, gw.output


async def test_a_board_that_resets_when_the_port_opens_costs_a_listener_one_gap(
    gateway_process: StartGateway, firmware: tuple[Path, Path]
) -> None:
    """An Arduino-like board: opening the port resets it (DTR) and a bootloader eats what comes for
    a second before the firmware greets. The firmware hangs; the gateway's keep-alive gives up and
    opens the port again, which resets the board: the gateway greets it again through the
    bootloader's second, and a listener sees exactly one gap."""
    harness, elf = firmware
    options = OPTIONS.replace("keepalive = 1.0", "keepalive = 1.0, keepalive_timeout = 2.0")
    with CProgram([str(harness), "--reset-on-open", "1000", str(elf)]) as board:
        url = f"serial://{board.where}?baudrate=115200"
        gw = gateway_process(f'[[services]]\nname = "thermo"\nurl = "{url}"\noptions = {options}\n')
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            setpoint = pb.GetRequest(service="thermo", property="setpoint")
            # The first open resets the board too: the gateway is connected once the firmware greets.
            first = await eventually(
                lambda: stub.Get(setpoint, timeout=WAIT), retry_on=(grpc.aio.AioRpcError,)
            )
            assert first.value == "20"
            stream = stub.Listen(pb.ListenRequest(service="thermo", property="temp"))
            gaps = 0
            async with asyncio.timeout(WAIT):
                assert (await stream.read()).events
                os.kill(board.proc.pid, signal.SIGUSR2)  # the firmware hangs
                after_gap = 0
                while after_gap < 4:  # the gap, then events for a while: no second gap
                    msg = await stream.read()
                    assert msg is not grpc.aio.EOF
                    gaps += sum(e.gap for e in msg.events)
                    after_gap += bool(gaps) * len(msg.events)
            stream.cancel()
            assert gaps == 1, f"{gw.output}\n{board.output}"
            assert (await stub.Get(setpoint, timeout=WAIT)).value == "20"
