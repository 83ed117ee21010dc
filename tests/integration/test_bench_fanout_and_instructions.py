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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import psutil
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


#: The runs of ``python -m bench.instructions --quick``, one round each: parts -> servers; the longest
#: first. Each server under callgrind spends most of a minute starting, and one start serves all the
#: parts of a run (``proxied`` has a start of its own), so the runs are as few as the ratios to the
#: bare server allow: the floor serves only the fan-outs.
INSTRUCTION_RUNS = {
    "unary,fanout,session,echo,proxied": "bare,gateway",
    "batched-fanout": "gateway,floor",
}
#: Runs at once where a core is idle: a server under callgrind starting keeps one core busy, and a
#: count does not move with the machine's load. On a machine already busy they go one at a time, as
#: a server that shares its core starts too slowly for the benchmark's start-up limit.
SIDE_BY_SIDE = 2
#: Seconds one run may take; and the tests that wait for all of them, one at a time on a busy machine.
RUN_TIMEOUT = 500
RUNS_TIMEOUT = 900
needs_valgrind = pytest.mark.skipif(
    shutil.which("callgrind_control") is None, reason="valgrind is not installed"
)


@pytest.fixture(scope="module")
def instruction_runs() -> dict[str, subprocess.CompletedProcess[str]]:
    """Each run of :data:`INSTRUCTION_RUNS`, finished, by its parts."""

    def run(parts: str) -> subprocess.CompletedProcess[str]:
        argv = ["--quick", "--rounds", "1", "--parts", parts, "--servers", INSTRUCTION_RUNS[parts]]
        return subprocess.run(
            [sys.executable, "-m", "bench.instructions", *argv],
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=RUN_TIMEOUT,
            check=False,
        )

    idle_cores = psutil.cpu_count() * (100.0 - psutil.cpu_percent(interval=1.0)) / 100.0
    at_once = SIDE_BY_SIDE if idle_cores >= 1.5 else 1
    print(f"bench.instructions runs: {at_once} at a time ({idle_cores:.1f} cores idle)")
    with ThreadPoolExecutor(max_workers=at_once) as pool:
        return dict(zip(INSTRUCTION_RUNS, pool.map(run, INSTRUCTION_RUNS), strict=True))


def _instructions_output(runs: dict[str, subprocess.CompletedProcess[str]], *parts: str) -> str:
    """The output of the runs that measured ``parts``, one after the other; each must have succeeded."""
    measured = [run for run in INSTRUCTION_RUNS if set(run.split(",")) & set(parts)]
    assert set(parts) <= {part for run in measured for part in run.split(",")}, parts
    for run in measured:
        assert runs[run].returncode == 0, runs[run].stdout + runs[run].stderr
    return "".join(runs[run].stdout for run in measured)


@needs_valgrind
@pytest.mark.timeout(RUNS_TIMEOUT)
def test_instructions_counts_a_get_and_an_event_on_each_server(
    instruction_runs: dict[str, subprocess.CompletedProcess[str]],
) -> None:
    out = _instructions_output(instruction_runs, "unary", "fanout")
    for part, per in (("unary", "Get"), ("fanout", "event")):
        for server in ("bare", "gateway"):
            assert re.search(rf"^{part}\s+{server}\s+instructions per {per}: [\d,]+ ", out, re.MULTILINE), out
        assert re.search(rf"^{part}\s+gateway\s+[\d.]+ x the bare server", out, re.MULTILINE), out


@needs_valgrind
@pytest.mark.timeout(RUNS_TIMEOUT)
def test_instructions_counts_a_session_get_beside_the_bare_servers_echo(
    instruction_runs: dict[str, subprocess.CompletedProcess[str]],
) -> None:
    out = _instructions_output(instruction_runs, "session", "echo")
    for part, server in (("session", "bare"), ("session", "gateway"), ("echo", "bare")):
        assert re.search(rf"^{part}\s+{server}\s+instructions per Get: [\d,]+ ", out, re.MULTILINE), out
    assert re.search(r"^session\s+gateway\s+[\d.]+ x the bare server", out, re.MULTILINE), out
    assert re.search(r"^echo\s+gateway\s+\(not measured", out, re.MULTILINE), out


@needs_valgrind
@pytest.mark.timeout(RUNS_TIMEOUT)
def test_instructions_counts_a_batched_event_on_the_gateway_and_the_floor(
    instruction_runs: dict[str, subprocess.CompletedProcess[str]],
) -> None:
    out = _instructions_output(instruction_runs, "batched-fanout")
    for server in ("gateway", "floor"):
        assert re.search(
            rf"^batched-fanout\s+{server}\s+instructions per event: [\d,]+ ", out, re.MULTILINE
        ), out


@needs_valgrind
@pytest.mark.timeout(RUNS_TIMEOUT)
def test_instructions_counts_a_get_through_the_line_proxy_on_the_gateway_only(
    instruction_runs: dict[str, subprocess.CompletedProcess[str]],
) -> None:
    out = _instructions_output(instruction_runs, "proxied")
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
