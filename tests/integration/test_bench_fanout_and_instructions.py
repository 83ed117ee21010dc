"""``python -m bench.fanout``, ``bench.instructions``, ``bench.hub_fanout`` and ``bench.paired`` run
end to end.

Smoke tests only: every server and every way ran to the end and printed a figure; never what
the figures are.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FIGURE = r"\s+[\d,.]+"


def _run(*args: str, timeout: float) -> str:
    done = subprocess.run(
        [sys.executable, "-m", *args],
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout


@pytest.mark.timeout(400)
def test_fanout_measures_every_server_mode_and_way() -> None:
    out = _run("bench.fanout", "--quick", "--rounds", "1", "--subscribers", "25", timeout=380)
    assert "no complete round" not in out, out
    for mode in ("one-by-one", "batched"):
        for server in ("floor", "bare", "gateway"):
            assert re.search(rf"^{mode}\s+{server}{FIGURE}{FIGURE}{FIGURE}", out, re.MULTILINE), out
    for way in ("a Listen stream each", "a Session each", "25 in a Session"):
        assert re.search(rf"^{way}{FIGURE}{FIGURE}{FIGURE}", out, re.MULTILINE), out


def _quick_instructions(parts: str, servers: str) -> str:
    """``python -m bench.instructions --quick`` of ``parts`` on ``servers``, one round: its output."""
    return _run(
        "bench.instructions", "--quick", "--rounds", "1", "--parts", parts, "--servers", servers, timeout=380
    )


@pytest.mark.skipif(shutil.which("callgrind_control") is None, reason="valgrind is not installed")
@pytest.mark.timeout(400)
def test_instructions_counts_a_get_and_an_event_on_each_server() -> None:
    out = _quick_instructions("unary,fanout", "bare,gateway")
    for part, per in (("unary", "Get"), ("fanout", "event")):
        for server in ("bare", "gateway"):
            assert re.search(rf"^{part}\s+{server}\s+instructions per {per}: [\d,]+ ", out, re.MULTILINE), out
        assert re.search(rf"^{part}\s+gateway\s+[\d.]+ x the bare server", out, re.MULTILINE), out


@pytest.mark.skipif(shutil.which("callgrind_control") is None, reason="valgrind is not installed")
@pytest.mark.timeout(400)
def test_instructions_counts_a_session_get_beside_the_bare_servers_echo() -> None:
    out = _quick_instructions("session,echo", "bare,gateway")
    for part, server in (("session", "bare"), ("session", "gateway"), ("echo", "bare")):
        assert re.search(rf"^{part}\s+{server}\s+instructions per Get: [\d,]+ ", out, re.MULTILINE), out
    assert re.search(r"^session\s+gateway\s+[\d.]+ x the bare server", out, re.MULTILINE), out
    assert re.search(r"^echo\s+gateway\s+\(not measured", out, re.MULTILINE), out


@pytest.mark.skipif(shutil.which("callgrind_control") is None, reason="valgrind is not installed")
@pytest.mark.timeout(400)
def test_instructions_counts_a_batched_event_on_the_gateway_and_the_floor() -> None:
    out = _quick_instructions("batched-fanout", "gateway,floor")
    for server in ("gateway", "floor"):
        assert re.search(
            rf"^batched-fanout\s+{server}\s+instructions per event: [\d,]+ ", out, re.MULTILINE
        ), out


@pytest.mark.skipif(shutil.which("callgrind_control") is None, reason="valgrind is not installed")
@pytest.mark.timeout(400)
def test_instructions_counts_a_get_through_the_line_proxy_on_the_gateway_only() -> None:
    out = _quick_instructions("proxied", "bare,gateway")
    assert re.search(
        r"^proxied\s+gateway\s+instructions per Get: [\d,]+ \([\d,]+ main\)", out, re.MULTILINE
    ), out
    assert re.search(r"^proxied\s+bare\s+\(not measured", out, re.MULTILINE), out


@pytest.mark.timeout(120)
def test_hub_fanout_times_an_event_and_a_message_of_the_hub_alone() -> None:
    out = _run("bench.hub_fanout", "--bursts", "5", timeout=100)
    assert re.search(
        r"^100 streams, 10 events a message: [\d.]+ µs per event, [\d.]+ µs per message", out, re.M
    ), out


@pytest.mark.timeout(300)
def test_paired_prints_both_ratios_for_one_and_eight_in_flight() -> None:
    out = _run("bench.paired", "--pairs", "2", "--calls", "200", timeout=280)
    for inflight in (1, 8):
        for figure in ("p50", "Gets/s"):
            head = rf"^{inflight} in flight, gateway / bare: {re.escape(figure)}"
            assert re.search(rf"{head} median [\d.]+, pairs [\d.]+-[\d.]+$", out, re.MULTILINE), out
