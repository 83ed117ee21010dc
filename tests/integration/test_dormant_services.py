"""Dormant services through a real gateway process: declared, woken by a call, stopped when idle.

A ``[[services]]`` entry with ``dormant = true`` is listed by the registry as
``dormant`` and not started; the first Get starts it (``ready``); after
``idle_stop`` seconds without use it is stopped (``dormant`` again); a licence
acquired on it wakes it too, and keeps it running while held.
"""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import pytest
from support.gateway_process import ROOT
from support.waiting import eventually, wait_until

from clients import AsyncClient
from clients.errors import Unavailable

CONFIG = """
[[services]]
name = "scout"
type = "sim-robot"

[[services]]
name = "spare"
type = "sim-robot"
dormant = true
idle_stop = 1
"""

STARTED = "service spare: dormant, starting it for a call"
STOPPED = "service spare: idle for 1 s, stopping it (dormant)"


async def test_a_dormant_service_is_woken_by_a_get_and_stopped_after_its_idle_time(gateway_process) -> None:  # type: ignore[no-untyped-def]
    gw = gateway_process(CONFIG)
    async with AsyncClient(gw.address) as client:
        assert await client.get("registry", "services.spare.availability") == "dormant"
        assert await client.get("registry", "services.spare.state") == "up"  # the old meaning holds
        assert await client.get("registry", "services.scout.availability") == "ready"
        assert STARTED not in gw.output
        seen: list[str] = []

        async def follow() -> None:
            async for event in client.listen("registry", "services.spare.availability"):
                seen.append(event.value)

        follower = asyncio.ensure_future(follow())
        try:
            await wait_until(lambda: seen == ["dormant"], what="the current availability")
            assert await client.get("spare", "location")  # the call wakes it and is answered
            # The gateway's log is read as it comes: wait for the line rather than assume it is in.
            await wait_until(lambda: STARTED in gw.output, what="the start logged")
            assert await client.get("registry", "services.spare.availability") == "ready"
            await wait_until(lambda: STOPPED in gw.output, within=10, what="the idle stop")
            await wait_until(lambda: seen[-1:] == ["dormant"] and len(seen) >= 3, what="dormant again")
            assert seen[:3] == ["dormant", "ready", "dormant"], seen
            # Woken again by the next call: a fresh start.
            await client.set("spare", "velocity", "(0.1 0)")
            await wait_until(lambda: gw.output.count(STARTED) == 2, what="the second start logged")
        finally:
            follower.cancel()


async def test_a_licence_wakes_a_dormant_service_and_keeps_it_running(gateway_process) -> None:  # type: ignore[no-untyped-def]
    gw = gateway_process(CONFIG)
    async with AsyncClient(gw.address) as client, client.session() as session:
        licence = await session.set("registry", "acquire", "", service="spare", duration="3")
        await wait_until(lambda: STARTED in gw.output, what="the start logged")
        assert await client.get("registry", "services.spare.availability") == "active"
        await asyncio.sleep(2)  # past idle_stop, with nobody calling: the licence keeps it running
        assert STOPPED not in gw.output
        await session.set("registry", "release", "", licence=licence)
        await eventually(
            lambda: client.get("registry", "services.spare.availability"), lambda v: v == "dormant", within=10
        )
        await wait_until(lambda: STOPPED in gw.output, what="the stop logged")


def test_check_config_reports_bad_dormancy_and_licence_limits(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(
        "[registry]\nmax_licences = 0\nmax_licence_duration = 100000\n"
        '[[services]]\nname = "spare"\ntype = "sim-robot"\nidle_stop = 5\n'
    )
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "check-config", str(bad)],
        cwd=ROOT, check=False, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert done.returncode == 2
    assert "registry.max_licences: must be at least 1, got 0" in done.stderr, done.stderr
    assert "registry.max_licence_duration: must be more than 0 and at most 86400 seconds" in done.stderr
    assert "idle_stop: only a dormant service (dormant = true) is stopped when idle" in done.stderr


async def test_a_woken_dormant_provider_is_scheduled_from_where_it_is(gateway_process) -> None:  # type: ignore[no-untyped-def]
    """Once awake, a dormant provider's location is read: it no longer counts as 0 away."""
    gw = gateway_process(
        """
        [[services]]
        name = "near"
        type = "sim-robot"
        features = ["survey"]
        options = { start = [1.0, 0.0] }

        [[services]]
        name = "far"
        type = "sim-robot"
        features = ["survey"]
        dormant = true
        options = { start = [5.0, 0.0] }
        """
    )
    async with AsyncClient(gw.address) as client, client.session() as session:
        assert await client.get("far", "location") == "(5 0 0 0 0 0)"  # the call wakes it
        assert await client.get("registry", "services.far.availability") == "ready"
        granted = await session.set("registry", "request", "(survey)", location="(0 0)")
        assert granted.startswith("(r1 granted ((near "), granted


async def test_the_idle_time_of_a_licensed_dormant_service_runs_from_the_licence_s_end(
    gateway_process,
) -> None:  # type: ignore[no-untyped-def]
    gw = gateway_process(CONFIG.replace("idle_stop = 1", "idle_stop = 3"))
    async with AsyncClient(gw.address) as client, client.session() as session:
        changes: list[tuple[str, float]] = []

        async def follow() -> None:
            async for event in client.listen("registry", "services.spare.availability"):
                changes.append((event.value, event.time.timestamp()))

        follower = asyncio.ensure_future(follow())
        try:
            licence = await session.set("registry", "acquire", "", service="spare", duration="1")
            await wait_until(
                lambda: changes[-1:] and changes[-1][0] == "dormant" and len(changes) > 2,
                within=15,
                what="dormant again",
            )
        finally:
            follower.cancel()
        marker = await client.get("registry", f"licences.{licence}")
        assert "<status>expired</status>" in marker
        ended = datetime.fromisoformat(
            marker.split("<expires>")[1].split("</expires>")[0].replace("Z", "+00:00")
        )
        assert changes[-1][1] - ended.timestamp() >= 3 - 0.1, (changes, marker)


async def test_a_dormant_device_that_does_not_answer_is_unavailable_before_the_call_s_deadline(
    gateway_process,
) -> None:  # type: ignore[no-untyped-def]
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    gw = gateway_process(
        f"""
        [[services]]
        name = "lost"
        url = "tcp://127.0.0.1:{port}"
        dormant = true
        features = ["survey"]

        [[services]]
        name = "near"
        type = "sim-robot"
        features = ["survey"]
        """
    )
    async with AsyncClient(gw.address) as client, client.session() as session:
        with pytest.raises(Unavailable, match="dormant and could not be started"):
            await client.get("lost", "properties")
        # The scheduler cannot wake it either: the request is refused as unavailable, not as if
        # nobody offered the service, and nothing stays allocated.
        with pytest.raises(Unavailable, match=r"could not be woken \(lost\)"):
            await session.set("registry", "request", "(survey)", count="2")
        assert await client.get("registry", "licences") == "()"
