"""Starting and stopping ``psgateway`` as a user does: each failure is one line and an exit code.

A port in use, a config error, Ctrl-C during start-up and Ctrl-C at the terminal (which signals
the whole foreground process group, device children included) — each through a real process.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from support.gateway_process import ROOT, GatewayProcess

EXIT_CONFIG = 2


def run_gateway(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        check=False,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


@pytest.fixture
def held_port() -> Iterator[int]:
    """A loopback port held by a listening socket of this test process."""
    with socket.socket() as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        yield holder.getsockname()[1]


def started_devices(output: str) -> list[str]:
    return [line for line in output.splitlines() if "device process" in line or "gateway.devices" in line]


def test_grpc_port_in_use_is_one_line_naming_the_port_and_holder(held_port: int) -> None:
    result = run_gateway("--listen", f"127.0.0.1:{held_port}", "--http", "127.0.0.1:0")
    assert result.returncode == EXIT_CONFIG
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if str(held_port) in line]
    assert errors == [
        f"psgateway: cannot start: port {held_port} (gateway.listen) is in use by "
        f"{Path(f'/proc/{os.getpid()}/comm').read_text().strip()} (pid {os.getpid()})"
    ]
    assert started_devices(result.stderr) == []  # the demo's device processes were never started


def test_line_port_in_use_is_one_line_too(held_port: int, tmp_path: Path) -> None:
    config = tmp_path / "line.toml"
    config.write_text(
        textwrap.dedent(f"""
            [gateway]
            line_listen = "127.0.0.1:{held_port}"
            [[devices]]
            name = "rover"
            type = "sim-robot"
            tcp = "127.0.0.1:0"
        """)
    )
    result = run_gateway("serve", "--config", str(config), "--listen", "127.0.0.1:0")
    assert result.returncode == EXIT_CONFIG
    assert "Traceback" not in result.stderr
    assert f"port {held_port} (gateway.line_listen) is in use by " in result.stderr
    assert started_devices(result.stderr) == []


def test_http_port_in_use_is_one_line_too(held_port: int, tmp_path: Path) -> None:
    config = tmp_path / "http.toml"
    config.write_text(
        textwrap.dedent("""
            [[devices]]
            name = "rover"
            type = "sim-robot"
            tcp = "127.0.0.1:0"
        """)
    )
    result = run_gateway(
        "serve", "--config", str(config), "--listen", "127.0.0.1:0", "--http", f"127.0.0.1:{held_port}"
    )
    assert result.returncode == EXIT_CONFIG
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if str(held_port) in line]
    assert errors == [
        f"psgateway: cannot start: port {held_port} (http.listen) is in use by "
        f"{Path(f'/proc/{os.getpid()}/comm').read_text().strip()} (pid {os.getpid()})"
    ]
    assert started_devices(result.stderr) == []


def test_a_device_too_slow_to_start_names_the_option_that_gives_it_longer(tmp_path: Path) -> None:
    config = tmp_path / "slow.toml"
    config.write_text(
        textwrap.dedent("""
            [gateway]
            device_start_timeout = 0.001
            [[devices]]
            name = "rover"
            type = "sim-robot"
            tcp = "127.0.0.1:0"
        """)
    )
    result = run_gateway("serve", "--config", str(config), "--listen", "127.0.0.1:0")
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    assert (
        "device rover: did not say where it serves within 0.001 s"
        " (raise [gateway] device_start_timeout on a loaded machine)" in result.stderr
    )


def test_serve_exits_2_on_an_unknown_service_type(tmp_path: Path) -> None:
    config = tmp_path / "unknown.toml"
    config.write_text('[[services]]\nname = "arm"\ntype = "robot-arm-9000"\n')
    result = run_gateway("serve", "--config", str(config), "--listen", "127.0.0.1:0")
    assert result.returncode == EXIT_CONFIG
    assert "Traceback" not in result.stderr
    assert (
        "config error" in result.stderr
        and "services (arm): unknown service type 'robot-arm-9000'" in result.stderr
    )


def test_check_config_reports_every_problem_in_one_run(tmp_path: Path) -> None:
    config = tmp_path / "many.toml"
    config.write_text(
        textwrap.dedent("""
            colour = "blue"
            [gateway]
            call_timeout = 0
            [limits]
            max_batch = 0
            [[services]]
            name = "a b"
            type = "sim-robot"
            [[services]]
            name = "nothing"
            [[devices]]
            name = "rover"
            type = "sim-robot"
        """)
    )
    result = run_gateway("check-config", str(config))
    assert result.returncode == EXIT_CONFIG
    problems = result.stderr.splitlines()
    assert all(line.startswith(f"psgateway: config error: {config}: ") for line in problems)
    for key in (
        "'colour'",
        "gateway.call_timeout",
        "limits.max_batch",
        "services[0].name",
        "services[1]",
        "devices[0]",
    ):
        assert sum(key in line for line in problems) == 1, (key, problems)


def test_check_config_reports_every_service_that_cannot_be_built(tmp_path: Path) -> None:
    config = tmp_path / "types.toml"
    config.write_text(
        '[[services]]\nname = "a"\ntype = "nope"\n[[services]]\nname = "b"\ntype = "nope-either"\n'
    )
    result = run_gateway("check-config", str(config))
    assert result.returncode == EXIT_CONFIG
    assert "services (a)" in result.stderr and "services (b)" in result.stderr


def test_check_config_takes_a_device_that_dials_in_as_serve_does(tmp_path: Path) -> None:
    config = tmp_path / "dial-in.toml"
    (tmp_path / "rover.secret").write_text("rover-secret-7f3a\n")
    config.write_text(
        '[gateway]\nline_listen = "127.0.0.1:7700"\n'
        '[[services]]\nname = "rover"\nurl = "tcp-in://"\nsecret_file = "rover.secret"\n'
    )
    result = run_gateway("check-config", str(config))
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"{config}: fine (1 services, listening on ")
    # Its secret file is still checked.
    (tmp_path / "rover.secret").unlink()
    missing = run_gateway("check-config", str(config))
    assert missing.returncode == EXIT_CONFIG
    assert "services[0] (rover).secret_file: cannot read" in missing.stderr


def test_client_ca_without_require_client_cert_is_noted_by_check_config_and_logged_at_start(
    tmp_path: Path,
) -> None:
    # The gRPC port names no caller by certificate then: a reader who set client_ca is told so.
    made = run_gateway("tls", "init", str(tmp_path / "certs"), "--host", "localhost", "--client", "op")
    assert made.returncode == 0, made.stderr
    certs = tmp_path / "certs"
    config = tmp_path / "optional.toml"
    config.write_text(
        '[gateway]\nlisten = "127.0.0.1:0"\n'
        f'[tls]\ncert = "{certs / "server.pem"}"\nkey = "{certs / "server.key"}"\n'
        f'client_ca = "{certs / "ca.pem"}"\n'
    )
    checked = run_gateway("check-config", str(config))
    assert checked.returncode == 0, checked.stderr
    note = "note: [tls] client_ca without require_client_cert: the gRPC port asks no client"
    assert note in checked.stdout
    gw = GatewayProcess([sys.executable, "-m", "gateway.cli", "serve", "--config", str(config)], {})
    try:
        gw.wait_ready(credentials=grpc.ssl_channel_credentials((certs / "ca.pem").read_bytes()))
        assert "client_ca without require_client_cert" in gw.output
    finally:
        gw.stop()
    required = config.read_text() + "require_client_cert = true\n"
    config.write_text(required)
    assert "note:" not in run_gateway("check-config", str(config)).stdout


def test_check_config_reports_keys_values_and_builds_together(tmp_path: Path) -> None:
    # Two bad keys in one section, a bad value beside them, and services that parse but do not
    # build: all in the first run, not a few at a time.
    config = tmp_path / "mixed.toml"
    config.write_text(
        textwrap.dedent("""
            [gateway]
            call_timout = 3
            log_level = "verbose"
            [limits]
            max_streams = -1
            [[services]]
            name = "scout3"
            type = "sim-robbot"
            [[services]]
            name = "scout4"
            type = "sim-robot"
            options = { sped = 2 }
            [[services]]
            name = "far"
            url = "ftp://x"
        """)
    )
    result = run_gateway("check-config", str(config))
    assert result.returncode == EXIT_CONFIG
    problems = result.stderr.splitlines()
    for key in (
        "gateway.call_timout: unknown key",
        "gateway.log_level",
        "limits.max_streams",
        "services (scout3): unknown service type",
        "services (scout4): bad options",
        "services (far)",
    ):
        assert sum(key in line for line in problems) == 1, (key, problems)
    assert len(problems) == 6, problems


def demo_in_own_group() -> GatewayProcess:
    """The demo gateway as a terminal runs it: Ctrl-C signals its whole process group."""
    return GatewayProcess(
        [sys.executable, "-m", "gateway", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"], own_group=True
    )


def wait_for_line(gw: GatewayProcess, text: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while text not in gw.output:
        assert time.monotonic() < deadline, gw.output
        assert gw.proc.poll() is None, gw.output
        time.sleep(0.01)


def test_ctrl_c_during_start_up_exits_cleanly() -> None:
    gw = demo_in_own_group()
    try:
        # Its in-process services are up, its device processes still booting: half way up.
        wait_for_line(gw, "service thermo1 started")
        os.killpg(gw.proc.pid, signal.SIGINT)
        assert gw.proc.wait(20) == 0
    finally:
        gw.stop()
    assert "Traceback" not in gw.output
    assert "WARNING" not in gw.output and "ERROR" not in gw.output
    assert "listening on" not in gw.output


def test_ctrl_c_of_the_demo_logs_no_device_warnings() -> None:
    gw = demo_in_own_group()
    try:
        gw.wait_ready()
        wait_for_line(gw, "service swarm started")
        os.killpg(gw.proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
        assert gw.proc.wait(20) == 0
    finally:
        gw.stop()
    assert "Traceback" not in gw.output
    assert "WARNING" not in gw.output, gw.output
    assert "multiple access on port" not in gw.output
    assert gw.output.count("stopped (pid") == 2  # rover1 and rover2 ended by the gateway
