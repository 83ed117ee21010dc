r"""``psgateway device-check`` run on every device of the project, and on devices broken on purpose.

The devices are real: the Python device server as a process (TCP, and its own pty with flow
control), the gateway's own line listener, the C library's example built for the host (TCP and a
pty), for the ATmega328P (in simavr) and for a Cortex-M3 (in QEMU), each on a pty. A broken
device is a real device behind a relay that breaks one rule of docs/device-spec.md in what passes
through; the kit must fail exactly the clauses of that rule.
"""

from __future__ import annotations

import asyncio
import re
import sys
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager
from pathlib import Path

import pytest
from line_device_support import ROOT, device_process, tcp_device
from support.c_device import CProgram, build
from support.gateway_process import StartGateway
from support.qemu_board import QemuBoard, require_qemu

from gateway.conformance import CLAUSES, FAIL, PASS, SKIP, Report, check_device
from gateway.conformance.probe import Probe, open_url

#: Seconds a device has for each reply. Generous: the machines are shared, and simavr runs the
#: AVR slower than real time.
REPLY_WAIT = 5.0
#: For a broken device, whose missing replies are waited for.
BROKEN_REPLY_WAIT = 1.0
COMMAND_WAIT = 120.0


def failures(report: Report) -> set[tuple[str, str]]:
    return {(o.number, o.title) for o in report.outcomes if o.status == FAIL}


def titled(words: str) -> tuple[str, str]:
    """The (number, title) of the one clause whose title holds ``words``."""
    (found,) = [(c.number, c.title) for c in CLAUSES if words in c.title]
    return found


def assert_conforms(report: Report, must_check: tuple[str, ...] = ()) -> None:
    shown = "\n".join(
        f"{o.status} §{o.number} {o.title}: {o.detail}\n  " + "\n  ".join(o.lines) for o in report.outcomes
    )
    assert not failures(report), shown
    assert len(report.outcomes) == len(CLAUSES) + 2, shown  # the greeting's two, then each clause
    checked = {o.number for o in report.outcomes if o.status == PASS}
    assert set(must_check) <= checked, shown


#: The clauses a device with a model, read-only, read-write and action properties lets the kit check.
EVERY_KIND = ("4.2", "4.1", "1.2", "2.3", "3.1", "3.2", "3.3", "3.6", "3.9", "6.2", "6.5", "9")


# -- the project's devices -----------------------------------------------------------------------


def test_the_python_device_server_conforms_on_tcp_and_the_command_exits_0() -> None:
    with tcp_device("--service", "sim-robot", "--name", "scout") as (host, port):
        import subprocess

        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "gateway",
                "device-check",
                f"tcp://{host}:{port}",
                "--timeout",
                str(REPLY_WAIT),
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=COMMAND_WAIT,
            check=False,
        )
    assert run.returncode == 0, run.stdout + run.stderr
    lines = run.stdout.splitlines()
    verdicts = [line for line in lines if re.match(r"(PASS|FAIL|SKIP)  §", line)]
    assert len(verdicts) == len(CLAUSES) + 2 and not any(v.startswith("FAIL") for v in verdicts)
    assert "device: HELLO 1 name=scout type=mobile_robot" in run.stdout
    assert re.search(r"^\d+ passed, 0 failed, \d+ skipped", run.stdout, re.M)


def test_the_python_device_server_conforms_on_its_own_pty_under_flow_control() -> None:
    args = ("--service", "sim-sensor", "--name", "therm", "--pty", "--inflight", "1", "--rxbuf", "32")
    with device_process(*args) as (_, first):
        pty = first.removeprefix("serial port ")
        report = asyncio.run(check_device(f"serial://{pty}?baudrate=115200", reply_wait=REPLY_WAIT))
    assert "inflight=1 rxbuf=32" in report.greeting
    assert_conforms(report, ("4.2", "1.2", "3.2", "3.3", "6.5", "9"))


def test_the_gateways_own_line_listener_conforms(gateway_process: StartGateway) -> None:
    gw = gateway_process(
        """
        [gateway]
        line_listen = "127.0.0.1:0"

        [[services]]
        name = "bot"
        type = "sim-robot"
        """
    )
    match = re.search(r"line-protocol listener on (127\.0\.0\.1:\d+)", gw.output)
    assert match, gw.output
    report = asyncio.run(check_device(f"tcp://{match.group(1)}", reply_wait=REPLY_WAIT))
    assert "name=gateway type=gateway" in report.greeting
    # Every service it lists answers a GET, as a namespace does: the names of its properties.
    assert_conforms(report, ("4.2", "1.2", "3.1", "3.3", "3.9", "6.5"))


@pytest.fixture(scope="module")
def c_build(tmp_path_factory: pytest.TempPathFactory) -> Path:
    into = tmp_path_factory.mktemp("c-build")
    build("host", into)
    return into


def test_the_c_library_conforms_on_tcp_and_on_a_pty(c_build: Path) -> None:
    thermostat = str(c_build / "host" / "thermostat")
    with CProgram([thermostat, "--tcp", "127.0.0.1:0"]) as device:
        report = asyncio.run(check_device(f"tcp://{device.where}", reply_wait=REPLY_WAIT))
    assert_conforms(report, EVERY_KIND)
    with CProgram([thermostat, "--pty"]) as device:
        report = asyncio.run(check_device(f"serial://{device.where}", reply_wait=REPLY_WAIT))
    assert_conforms(report, EVERY_KIND)


#: A reading that changes while the vectors run: compared as "a number".
READING = re.compile(r"^((?:#\w+ )?OK) -?\d+(?:\.\d+)?$")


def spec_vectors() -> list[tuple[str, list[str]]]:
    """Each request line of docs/device-spec.md §10 with the lines answering it (EVENTs left out)."""
    text = (ROOT / "docs" / "device-spec.md").read_text(encoding="utf-8")
    block = text.split("## 10. Test vectors", 1)[1].split("```", 2)[1]
    exchanges: list[tuple[str, list[str]]] = []
    for line in block.splitlines():
        if line.startswith("> "):
            exchanges.append((line[2:], []))
        elif line.startswith("< ") and exchanges and not line.startswith("< EVENT "):
            exchanges[-1][1].append(line[2:])
    return exchanges


def comparable(request: str, line: str) -> str:
    """``line`` with what may differ between two conforming devices put aside: the greeting's
    fields (each device states its own) and a sensor's reading."""
    line = re.sub(r"HELLO 1 .*", "HELLO 1 ...", line)
    return READING.sub(r"\1 <reading>", line) if " temp" in request else line


async def exchange_vectors(url: str) -> list[tuple[str, list[str], list[str]]]:
    """Send each vector's request; (request, expected, answered), both made comparable."""
    reader, writer = await open_url(url)
    probe = Probe(reader, writer, REPLY_WAIT)
    try:
        assert await probe.line() is not None  # the greeting
        results = []
        for request, expected in spec_vectors():
            await probe.send(request.encode())
            answered = []
            for _ in expected:
                heard = await probe.reply()
                answered.append(heard.text if heard is not None else "(nothing)")
            if not expected and (heard := await probe.reply(0.3)) is not None:
                answered.append(heard.text)
            results.append(
                (
                    request,
                    [comparable(request, e) for e in expected],
                    [comparable(request, a) for a in answered],
                )
            )
        return results
    finally:
        await probe.close()


def test_the_c_library_answers_the_test_vectors_of_the_specification_byte_for_byte(c_build: Path) -> None:
    with CProgram([str(c_build / "host" / "thermostat"), "--tcp", "127.0.0.1:0"]) as device:
        results = asyncio.run(exchange_vectors(f"tcp://{device.where}"))
    assert len(results) > 20
    differing = [
        (request, expected, answered) for request, expected, answered in results if expected != answered
    ]
    assert not differing, differing


def test_the_avr_firmware_conforms_in_simavr(tmp_path: Path) -> None:
    build("avr", tmp_path)
    build("sim", tmp_path)
    with CProgram([str(tmp_path / "sim" / "simavr_uart"), str(tmp_path / "avr" / "thermostat.elf")]) as mcu:
        report = asyncio.run(
            check_device(f"serial://{mcu.where}?baudrate=115200", reply_wait=REPLY_WAIT, greeting_wait=10.0)
        )
    assert re.search(r"maxline=64 inflight=1 rxbuf=\d+", report.greeting), report.outcomes[:2]
    assert_conforms(report, EVERY_KIND)


def test_the_cortex_m_firmware_conforms_in_qemu(tmp_path: Path) -> None:
    require_qemu()
    build("cortexm", tmp_path)
    with QemuBoard(tmp_path / "cortexm" / "thermostat.elf", tmp_path) as board:
        report = asyncio.run(
            check_device(f"serial://{board.where}?baudrate=115200", reply_wait=REPLY_WAIT, greeting_wait=10.0)
        )
    assert re.search(r"name=thermo1 .*inflight=1", report.greeting), report.outcomes[:2]
    assert_conforms(report, EVERY_KIND)


# -- broken devices ------------------------------------------------------------------------------

Rewrite = Callable[[bytes], bytes | None]


def _same(line: bytes) -> bytes | None:
    return line


@asynccontextmanager
async def breaking_relay(
    device: tuple[str, int], to_device: Rewrite = _same, to_client: Rewrite = _same
) -> AsyncIterator[str]:
    """A relay on a free port in front of ``device`` that passes each line through a rewrite
    (None drops it); yields its ``tcp://`` URL."""
    tasks: set[asyncio.Task[None]] = set()

    async def pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, rewrite: Rewrite) -> None:
        try:
            while line := await reader.readline():
                changed = rewrite(line.rstrip(b"\n"))
                if changed is not None:
                    writer.write(changed + b"\n")
                    await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()

    async def serve(client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        device_reader, device_writer = await asyncio.open_connection(*device)
        for task in (
            asyncio.create_task(pump(client_reader, device_writer, to_device)),
            asyncio.create_task(pump(device_reader, client_writer, to_client)),
        ):
            tasks.add(task)
            task.add_done_callback(tasks.discard)

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        yield f"tcp://127.0.0.1:{port}"
    finally:
        server.close()
        for task in list(tasks):
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def _unescape_pong(line: bytes) -> bytes:
    return line.replace(b"\\s", b" ").replace(b"\\\\", b"\\") if b" PONG " in line else line


def _drop_replies(line: bytes) -> bytes | None:
    words = line.split()
    word = words[1] if words and words[0].startswith(b"#") and len(words) > 1 else words[0] if words else b""
    return None if word in (b"OK", b"ERR", b"EVENT", b"GONE") else line


def _strip_checksums(line: bytes) -> bytes:
    return line[1:-3] if line.startswith(b"$") and line[-3:-2] == b"*" else line


def _any_case_paths(line: bytes) -> bytes:
    head, word, path = line.partition(b"GET ")
    return head + word + path.lower() if word else line


BREAKS = {
    "unescapes PING data": ({"to_client": _unescape_pong}, {titled("PING data is echoed")}),
    "ignores replies sent to it": ({"to_device": _drop_replies}, {titled("OK, ERR, EVENT and GONE")}),
    "never sends a checksum": (
        {"to_client": _strip_checksums},
        {
            titled("wrong checksum"),
            titled("carries the right checksum"),
            titled("every line goes out checked"),
        },
    ),
    "takes paths in any case": ({"to_device": _any_case_paths}, {titled("paths are case-sensitive")}),
}


@pytest.fixture(scope="module")
def robot() -> Iterator[tuple[str, int]]:
    with tcp_device("--service", "sim-robot", "--name", "scout") as where:
        yield where


@pytest.mark.parametrize("broken", list(BREAKS))
def test_a_device_that_breaks_a_rule_fails_exactly_its_clauses(robot: tuple[str, int], broken: str) -> None:
    rewrites, expected = BREAKS[broken]

    async def run() -> Report:
        async with breaking_relay(robot, **rewrites) as url:
            return await check_device(url, reply_wait=BROKEN_REPLY_WAIT)

    report = asyncio.run(run())
    assert failures(report) == expected, [
        (o.number, o.title, o.detail) for o in report.outcomes if o.status == FAIL
    ]
    for outcome in report.outcomes:
        if outcome.status == FAIL:
            assert outcome.detail and any(line.startswith("> ") for line in outcome.lines)
    assert not any(o.status == SKIP and o.number == "4.1" for o in report.outcomes)


def test_the_command_shows_the_wire_lines_of_a_failure_and_exits_1(robot: tuple[str, int]) -> None:
    async def run() -> tuple[int, str]:
        async with breaking_relay(robot, to_client=_unescape_pong) as url:
            proc = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "gateway",
                "device-check",
                url,
                "--timeout",
                str(BROKEN_REPLY_WAIT),
                cwd=ROOT,
                stdout=asyncio.subprocess.PIPE,
            )
            out, _ = await asyncio.wait_for(proc.communicate(), COMMAND_WAIT)
            return proc.returncode or 0, out.decode()

    code, out = asyncio.run(run())
    assert code == 1, out
    assert re.search(r"^FAIL  §3\.6 +PING data is echoed byte for byte$", out, re.M), out
    assert re.search(r"^      > #k\w+ PING conformance a\\sb\\\\c  d$", out, re.M), out
    assert re.search(r"^      < #k\w+ PONG conformance a b\\c  d$", out, re.M), out
    assert re.search(r"^\d+ passed, 1 failed, \d+ skipped", out, re.M), out


def test_an_unreachable_device_exits_2_and_help_says_what_the_exit_codes_mean() -> None:
    import socket
    import subprocess

    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]  # bound, never listening: the connection is refused
        run = subprocess.run(
            [sys.executable, "-m", "gateway", "device-check", f"tcp://127.0.0.1:{port}"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=COMMAND_WAIT,
            check=False,
        )
    assert run.returncode == 2 and "cannot reach the device" in run.stderr, run.stderr
    helped = subprocess.run(
        [sys.executable, "-m", "gateway", "device-check", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=COMMAND_WAIT,
        check=True,
    ).stdout
    for words in ("tcp://", "serial://", "docs/device-spec.md", "Exit status", "--read-only", "rxbuf"):
        assert words in helped, helped
