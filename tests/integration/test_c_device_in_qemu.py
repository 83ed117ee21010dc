"""The example device's Cortex-M firmware (an LM3S6965, built with Debian's gcc-arm-none-eabi) in QEMU's
lm3s6965evb with UART0 on a host pty, driven by a real gateway's serial proxy: Get, Set, Listen, a
reset from QEMU's monitor, a binary value, and the gateway keeping to the device's flow control
(inflight=1 rxbuf=128). Its flash and RAM, against the ATmega328P's budget."""

from __future__ import annotations

import asyncio
import os
import re
import select
import subprocess
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from support.c_device import build
from support.gateway_process import StartGateway
from support.qemu_board import SRAM_SIZE, QemuBoard, require_qemu, untouched
from support.serial_tap import WireTap
from support.thermostat import assert_a_reset_mid_listen_is_a_gap, run_psctl

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 20.0
RXBUF = 128
GREETING = "HELLO 1 name=thermo1 type=sensor push=1 maxline=128 inflight=1 rxbuf=128"
#: The same budget as the ATmega328P's (docs/c-device-library.md): the library is no bigger here.
FLASH_BUDGET = 8 * 1024
RAM_BUDGET = 1024
#: Silence that means the device has answered all it will (it answers within microseconds in QEMU).
QUIET = 0.5
OPTIONS = "{ timeout = 5.0, backoff_initial = 0.05, backoff_max = 0.5, keepalive = 1.0 }"


@pytest.fixture(scope="module")
def firmware(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """(the firmware ELF, the build's output with arm-none-eabi-size's table)."""
    into = tmp_path_factory.mktemp("cortexm-build")
    output = build("cortexm", into)
    return into / "cortexm" / "thermostat.elf", output


@pytest.fixture
def board(firmware: tuple[Path, str], tmp_path: Path) -> Iterator[QemuBoard]:
    require_qemu()
    with QemuBoard(firmware[0], tmp_path) as running:
        yield running


def test_the_cortex_m_firmware_fits_the_budget_and_links_no_float_or_malloc(
    firmware: tuple[Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    elf, output = firmware
    # arm-none-eabi-size's Berkeley table: text data bss dec hex filename
    sizes = re.search(r"^\s*(\d+)\s+(\d+)\s+(\d+)\s+\d+\s+[0-9a-f]+\s+\S+thermostat\.elf$", output, re.M)
    assert sizes, output
    text, data, bss = (int(g) for g in sizes.groups())
    with capsys.disabled():
        print(f"\nLM3S6965 example device: flash {text + data} bytes, RAM {data + bss} bytes (static)")
    assert text + data <= FLASH_BUDGET, output
    assert data + bss <= RAM_BUDGET, output
    assert (elf.parent / "thermostat.bin").stat().st_size == text + data, "the flash image is written too"
    nm = subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True)
    symbols = nm.stdout
    # The vector table sits at 0, where the core reads its stack pointer and reset address.
    assert re.search(r"^00000000 \w vectors$", symbols, re.M), symbols
    # No floating point (the EABI's soft-float helpers) and no heap are linked in.
    for routine in ("malloc", "_sbrk", "__aeabi_fadd", "__aeabi_fmul", "__aeabi_dadd", "__aeabi_i2f"):
        assert not re.search(rf"\b{routine}\b", symbols), f"{routine} is linked in"


def read_until(fd: int, ending: str | None) -> str:
    """What the device sends until its output ends with ``ending`` (None: until it falls silent for
    QUIET seconds), at most WAIT seconds."""
    out = b""
    deadline = time.monotonic() + WAIT
    while (left := deadline - time.monotonic()) > 0:
        if select.select([fd], [], [], min(left, QUIET))[0]:
            out += os.read(fd, 65536)
            if ending is not None and out.decode().endswith(ending):
                break
        elif ending is None and out:
            break
    return out.decode()


def test_a_burst_past_the_ring_marks_every_loss_and_merges_no_lines(board: QemuBoard) -> None:
    """The control experiment, no gateway: 1.7 KB of requests at once while the device writes long
    replies overflow its 128-byte ring, often several times. Each damaged line is answered ERR 15
    (untagged), every other one as sent: no two lines are read as one."""
    fd = os.open(board.where, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        # Bytes that come before the firmware has set up its UART are lost, as on a real board: ask
        # until the greeting's answer comes.
        deadline = time.monotonic() + WAIT
        while "#hi HELLO 1 " not in (os.write(fd, b"#hi HELLO\n"), read_until(fd, None))[1]:
            assert time.monotonic() < deadline, "the firmware never answered HELLO"
        burst = b"GET properties.model\n" * 10 + b"".join(b"#%d GET setpoint\n" % n for n in range(100))
        # Whether a burst overflows depends on how QEMU's threads are scheduled: send it again (at
        # most five times) until one did. Every burst's replies are checked alike below.
        answers = []
        for attempt in range(5):
            os.write(fd, burst)
            answer = read_until(fd, None)
            # The burst's last line may have lost its LF: the next LF ends it (ERR 15), and the line
            # after that is read afresh.
            os.write(fd, b"\n#last%d GET setpoint\n" % attempt)
            answer += read_until(fd, f"#last{attempt} OK 20\n")
            answers.append(answer)
            if "ERR 15 bytes lost" in answer:
                break
    finally:
        os.close(fd)
    answer = answers[-1]
    replies = answer.rstrip("\n").split("\n")
    lost = [line for line in replies if line.startswith("ERR 15 bytes lost")]
    answered = [int(n) for n in re.findall(r"^#(\d+) OK 20$", answer, re.M)]
    for earlier in answers[:-1]:  # a burst that lost nothing was answered line by line, as sent
        assert re.findall(r"^#(\d+) OK 20$", earlier, re.M) == [str(n) for n in range(100)], earlier
    assert lost, answer
    assert all(line.startswith(("OK ((temp", "#", "ERR 15 bytes lost")) for line in replies), answer
    assert "ERR" not in answer.replace("ERR 15 bytes lost", ""), "a merged line was read as a request"
    assert answered == sorted(set(answered)) and len(answered) + len(lost) <= 110, answer
    assert replies[-1] == f"#last{len(answers) - 1} OK 20", "the next line is read afresh"


async def test_the_firmware_in_qemu_through_the_gateway(
    gateway_process: StartGateway, board: QemuBoard, capsys: pytest.CaptureFixture[str]
) -> None:
    with WireTap(board.where) as tap:
        gw = gateway_process(
            f'[[services]]\nname = "thermo"\nurl = "serial://{tap.path}?baudrate=115200"\n'
            f"options = {OPTIONS}\n"
        )
        shown: list[str] = []
        run = lambda *args: asyncio.to_thread(run_psctl, gw.address, shown, *args)  # noqa: E731
        five = await run("get", "thermo", "temp", "setpoint", "location", "label", "temp.gui")
        assert "setpoint = 20\n" in five and "label = bench" in five and "temp.gui = gauge" in five, five
        # A 40-byte request: more than the AVR's 32-byte ring takes, within this board's 128.
        assert "(10.25 20.5 0 0 0 0)" in await run("set", "thermo", "location", "(10.25 20.5 0 0 0 0)")
        events = await run("listen", "thermo", "temp", "--count", "3")
        assert len(re.findall(r"thermo temp = ", events)) == 3, events
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await stub.Set(pb.SetRequest(service="thermo", property="setpoint", value="23.5"), timeout=WAIT)
            x = await stub.Get(pb.GetRequest(service="thermo", property="location.x"), timeout=WAIT)
            assert x.value == "10.25"
            # A reset from QEMU's monitor mid-Listen: the firmware starts afresh from its vector table.
            await assert_a_reset_mid_listen_is_a_gap(stub, board.reset)
        transcript = tap.transcript()
        assert "ERR" not in transcript, transcript
        # Greeted at least twice: in answer to the gateway's HELLO and after the reset.
        assert transcript.count(f"< {GREETING}") >= 2, transcript
        assert re.search(r"^< #\w+ PONG", transcript, re.M), "the device answered the gateway's keep-alive"
        assert 0 < tap.most_unanswered_bytes() <= RXBUF, transcript
    # The deepest the stack went since the reset, with the static data: SRAM the start-up code painted
    # and nothing wrote since.
    used = SRAM_SIZE - untouched(board.sram())
    assert used <= RAM_BUDGET, f"{used} bytes of SRAM used"
    with capsys.disabled():
        print("\n--- psctl against the gateway, the Cortex-M firmware in QEMU ---")
        print("\n".join(shown))
        print(f"--- the serial line (> gateway, < device), {len(tap.record())} lines; RAM used: {used} B")
        print("\n".join(transcript.split("\n")[:24]))
