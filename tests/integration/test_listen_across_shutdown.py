"""A Listen the gateway ends is not a clean end: psctl exits non-zero, and the SDK can resume."""

from __future__ import annotations

import subprocess
import time

import pytest
from support.gateway_process import StartGateway
from support.ports import free_port
from support.psctl import PSCTL

from clients.aio import Event
from clients.errors import Unavailable
from clients.sync import Client

SENSOR = """
    [[services]]
    name = "thermo"
    type = "sim-sensor"
"""


def test_psctl_listen_exits_1_when_the_gateway_shuts_down(gateway_process: StartGateway) -> None:
    gw = gateway_process(SENSOR)
    listen = subprocess.Popen(
        [*PSCTL, "-t", gw.address, "listen", "thermo", "data", "--marks"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert listen.stdout is not None
        while "-- sync" not in listen.stdout.readline():
            pass
        assert gw.stop() == 0
        _, err = listen.communicate(timeout=30)
    finally:
        if listen.poll() is None:
            listen.kill()
            listen.wait()
    assert listen.returncode == 1
    assert "UNAVAILABLE" in err and "gateway shutting down" in err


def test_psctl_listen_exits_0_at_its_count(gateway_process: StartGateway) -> None:
    gw = gateway_process(SENSOR)
    done = subprocess.run(
        [*PSCTL, "-t", gw.address, "listen", "thermo", "data", "--count", "2"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert len(done.stdout.splitlines()) == 2


def test_a_resumed_listen_carries_on_after_a_restart_and_marks_the_gap(gateway_process: StartGateway) -> None:
    port = free_port()
    address = f"127.0.0.1:{port}"
    first = gateway_process(SENSOR, extra_args=["--listen", address])
    with Client(address, timeout=10) as client:
        events = client.listen("thermo", "data", resume=True)
        try:
            before = next(events)
            assert isinstance(before, Event) and not before.gap
            first.stop()
            # The stream does not end: the SDK waits for the gateway to come back.
            started = time.monotonic()
            gateway_process(SENSOR, extra_args=["--listen", address])
            after = next(events)
            assert after.gap, after  # values of the time between may be lost
            assert after.sequence == 1  # a new stream
            assert not next(events).gap
            assert time.monotonic() - started < 30
        finally:
            events.close()


def test_without_resume_the_sdk_raises_unavailable(gateway_process: StartGateway) -> None:
    gw = gateway_process(SENSOR)
    with Client(gw.address, timeout=10) as client:
        events = client.listen("thermo", "data")
        try:
            next(events)
            gw.stop()
            try:
                while True:
                    next(events)
            except Unavailable as exc:
                assert "gateway shutting down" in str(exc)
        finally:
            events.close()


def test_a_session_refuses_resume(gateway_process: StartGateway) -> None:
    gw = gateway_process(SENSOR)
    with (
        Client(gw.address) as client,
        client.session() as session,
        pytest.raises(ValueError, match="resume"),
    ):
        next(session.listen("thermo", "data", resume=True))
