"""``python -m gateway.cluster``: etcd and three gateways with devices, started and stopped by one command."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support.cluster_command import ClusterCommand
from support.etcd import etcd_binary
from support.waiting import eventually

from clients import AsyncClient

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

ROOT = Path(__file__).resolve().parents[2]
_GATEWAY_ROW = re.compile(r"^(gw\d)\s+(127\.0\.0\.1:\d+)\s+http://\S+/\s+127\.0\.0\.1:\d+\s+(.*)$")
_DEVICE_ROW = re.compile(r"^((?:thermo|rover)\d+)\s+(\S+)\s+(\S+)$")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A child that ended but was not reaped yet is a zombie: not running.
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().split(") ")[-1][:1] != "Z"


async def test_one_command_starts_a_cluster_that_answers_everywhere_and_stops_it_all() -> None:
    etcd_binary()  # skips, saying why, without etcd
    command = ClusterCommand(["--gateways", "3", "--devices", "5", "--base-port", "0", "--lease", "2"])
    try:
        command.wait_for("cluster ready")
        gateways = {m.group(1): (m.group(2), m.group(3)) for m in map(_GATEWAY_ROW.match, command.lines) if m}
        devices = {m.group(1): m.group(3) for m in map(_DEVICE_ROW.match, command.lines) if m}
        # --base-port 0 picks etcd's ports free too: it runs beside an etcd on 2379.
        assert not command.line("etcd:").startswith("etcd: etcd://127.0.0.1:2379 ")
        assert sorted(gateways) == ["gw1", "gw2", "gw3"]
        assert len(devices) == 5
        assert set(devices.values()) <= set(gateways), devices  # every device has a live owner
        assert len(set(devices.values())) == 3  # spread over the three gateways
        pids = command.pids()
        assert len(pids) == 1 + 3 + 5  # etcd, the gateways, the devices
        for name, (address, _) in gateways.items():
            async with AsyncClient(address) as client:
                listed = await eventually(
                    lambda c=client: c.get_names("registry", "services"),
                    lambda names: set(devices) <= set(names),
                )
                assert set(devices) <= set(listed), name
                for device, owner in devices.items():
                    # Any gateway answers for any device: its own, or forwarded to the owner.
                    assert await client.get("registry", f"services.{device}.owner") == owner
                    assert await client.get_names(device, "properties")
    finally:
        status = command.stop()
    assert status == 0, "\n".join(command.lines)
    assert command.lines[-1] == "stopped"
    for what, pid in pids.items():
        assert not _alive(int(pid)), f"{what} (pid {pid}) still runs"


def test_without_etcd_it_says_what_to_install(tmp_path: Path) -> None:
    python_only = tmp_path / "bin"
    python_only.mkdir()
    (python_only / "python").symlink_to(sys.executable)
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cluster", "--once"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "PATH": str(python_only)},
        timeout=60,
        check=False,
    )
    assert done.returncode == 2
    assert "etcd is not installed" in done.stderr
    assert "apt-get install etcd-server" in done.stderr


def test_an_etcd_port_in_use_is_named_with_what_to_do() -> None:
    etcd_binary()  # skips, saying why, without etcd
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run(
            [sys.executable, "-m", "gateway.cluster", "--once", "--etcd-port", str(port)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    assert done.returncode == 1, done.stderr
    assert f"error: port {port} (etcd's client port) is in use by " in done.stderr
    assert "--etcd-port 0 picks free ones" in done.stderr
    assert "Traceback" not in done.stderr
    assert "kept in" not in done.stderr  # nothing started, no empty folder left behind


def test_help_names_the_ports_and_the_picture() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cluster", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    )
    for option in ("--gateways", "--devices", "--base-port", "--etcd-port", "--lease", "--picture", "--once"):
        assert option in done.stdout
    assert "Ctrl-C stops everything" in done.stdout


def test_a_gateway_killed_is_named_and_its_devices_shown_with_their_new_owners() -> None:
    etcd_binary()  # skips, saying why, without etcd
    command = ClusterCommand(["--gateways", "3", "--devices", "6", "--base-port", "0", "--lease", "2"])
    try:
        command.wait_for("cluster ready")
        before = {m.group(1): m.group(3) for m in map(_DEVICE_ROW.match, command.lines) if m}
        registered = {m.group(1): m.group(2) for m in map(_DEVICE_ROW.match, command.lines) if m}
        pids = command.pids()
        victim = before["rover1"] if "rover1" in before else sorted(set(before.values()))[0]
        moved = sorted(name for name, owner in before.items() if owner == victim)
        assert moved, before
        printed = len(command.lines)
        os.kill(int(pids[victim]), signal.SIGKILL)  # a process the command started, by its PID
        command.wait_for(f"{victim} (pid {pids[victim]}) exited with status -9")
        command.wait_for("waiting ")
        after: dict[str, str] = {}

        def new_table() -> bool:
            lines = command.lines[printed:]
            starts = [i for i, line in enumerate(lines) if line.startswith("device ")]
            if not starts:
                return False
            rows = [_DEVICE_ROW.match(line) for line in lines[starts[-1] + 1 :]]
            after.clear()
            after.update({m.group(1): m.group(3) for m in rows if m})
            return len(after) == len(before)

        deadline = time.monotonic() + 60
        while not new_table():
            assert time.monotonic() < deadline, "\n".join(command.lines)
            time.sleep(0.1)
        # The dead gateway owns nothing and is gone from the gateways' table; every device it owned
        # by URL has a live owner, and the others kept theirs.
        assert victim not in after.values(), after
        rows = [m.group(1) for m in map(_GATEWAY_ROW.match, command.lines[printed:]) if m]
        assert rows and victim not in rows, command.lines[printed:]
        for name in moved:
            if registered[name].startswith("tcp://"):
                assert after[name] in set(before.values()) - {victim}, (name, after)
        for name, owner in before.items():
            if owner != victim:
                assert after[name] == owner, (name, before, after)
    finally:
        status = command.stop()
    assert status == 0, "\n".join(command.lines)
