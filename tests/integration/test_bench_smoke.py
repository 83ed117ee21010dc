"""The benchmark runs end to end: ``python -m bench --quick`` measures both servers and judges every target.

A smoke test only: it checks that each part ran on both servers and that
every ratio line carries a figure and a verdict, never what the figures are.
So the sizes are smaller still than ``--quick``'s (each part's size options, given on the command
line as a user would): every part runs, on every server, at two sizes where it has sizes, in
about half the time.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TARGETS = (
    "unary-get",
    "session-get",
    "listen-fanout",
    "listen-batched",
    "idle-listen-memory",
    "line-get-p50",
    "line-get-inflight",
    "line-session-p50",
    "line-session-inflight",
    "line-session-proxy-cost",
    "line-inflight-ceiling",
    "group-moveto",
    "group-scaling",
    "find-p99",
    "find-scaling",
    "register-rate",
    "register-scaling",
    "register-memory",
    "tls-unary",
    "tls-session",
    "storage-set-1k",
    "storage-set-1m",
    "sse-fanout",
    "sse-latency-p50",
    "sse-latency-p99",
    "rosbridge-fanout",
    "rosbridge-latency-p50",
    "statemachine",
    "scheduler",
    "camera-fps",
    "camera-cores",
    "recording-cpu",
    "fusion-scaling",
    "metrics-unary",
    "session-floor-p50",
    "session-floor-p99",
    "unary-p50-rounds",
    "unary-inflight-rounds",
    "fanout-unbatched",
    "fanout-batched-10x",
    "fanout-paced-p50",
    "proxy-session-p50",
    "session-listen-memory",
    "cluster-cores",
    "cluster-register-rate",
    "cluster-forwarded-get",
)
#: The peers of part (s); each either ran every pattern or says why it was skipped.
PEERS = ("opcua", "zenoh")
#: Targets of the registry on etcd: not run (and said so) on a machine without etcd.
NEED_ETCD = ("cluster-register-rate", "cluster-forwarded-get")
#: Gets one at a time and in flight (a), (q), (s); Sets each subscriber hears (c), (j); devices that
#: register (h), and that register across four gateways on etcd (t).
CALLS = 500
SETS = 50
REGISTER_SIZES = (200, 400)
CLUSTER_DEVICES = 100
#: Smaller than --quick's sizes; the parts not named here are quick enough at --quick's own.
SIZES = {
    "--calls": CALLS,
    "--warmup": 50,
    "--session-gets": 2_000,
    "--subscribers": 50,
    "--sets": SETS,
    "--paced-sets": 20,
    "--peer-sets": 20,
    "--streams": 100,
    "--line-calls": 200,
    "--register-sizes": ",".join(map(str, REGISTER_SIZES)),
    "--storage-calls": 50,
    "--scheduler-sizes": "100,1000",
    "--scheduler-rounds": 20,
    "--camera-seconds": 1,
    "--recording-seconds": 1,
    "--cmd-vel-trips": 20,
    "--fusion-sizes": "100,1000",
    "--fusion-observations": 500,
    "--cluster-streams": 40,
    "--cluster-seconds": 1,
    "--cluster-devices": CLUSTER_DEVICES,
    "--cluster-queries": 50,
}


# Every part of the bench, each once, on a shared 2-core machine: about 1.5 minutes when it is quiet at
# --quick's sizes, six under load (the cluster part, which starts etcd, 4 gateways and their devices, and
# gateways 7 times for the cores, is the largest); the smaller sizes here save about a third.
@pytest.mark.timeout(620)
def test_quick_bench_prints_every_ratio(tmp_path: Path) -> None:
    saved = tmp_path / "bench.json"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "bench",
            "--quick",
            "--json",
            str(saved),
            *(str(word) for option in SIZES.items() for word in option),
        ],
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    assert re.search(r"^machine: .+ \d+ cores .*grpcio \d", out, re.MULTILINE), out
    has_etcd = shutil.which("etcd") is not None
    if not has_etcd:
        print(
            f"etcd is not installed: {', '.join(NEED_ETCD)} are not run (tests/run.sh installs etcd-server)"
        )
    for name in TARGETS:
        if name in NEED_ETCD and not has_etcd:
            assert re.search(rf"^ratio {name} +n/a .*NOT RUN", out, re.MULTILINE), out
            continue
        line = re.search(rf"^ratio {name} +(\S+) .*target [<>]= [\d.]+ \S+ +(PASS|FAIL)\b", out, re.MULTILINE)
        assert line is not None, f"no judged ratio line for {name}:\n{out}"
        float(line.group(1))

    payload = json.loads(saved.read_text())
    for server in ("baseline", "gateway"):
        for part in ("unary", "session", "listen", "batched", "memory", "sequential", "paced"):
            figures = payload["results"][server][part]
            assert "error" not in figures, (server, part, figures)
    # Every Set reached every subscriber, on both servers (delivered or, for the gateway, conflated).
    for server in ("baseline", "gateway"):
        listen = payload["results"][server]["listen"]
        assert listen["complete"], listen
        assert listen["events"] + listen["conflated"] == listen["expected_events"]
    assert payload["results"]["gateway"]["batched"]["events_per_message"] > 1
    # Gets one at a time: unary and Session on both servers, and the bare server's echo floor; every call
    # answered, each round's figures kept (the unary targets are judged per round).
    for server, ways in (("baseline", ["unary", "session", "echo"]), ("gateway", ["unary", "session"])):
        sequential = payload["results"][server]["sequential"]
        assert list(sequential["ways"]) == ways, sequential
        for figures in sequential["ways"].values():
            assert figures["done"] == CALLS and figures["errors"] == 0 and figures["latency"]["p50_us"] > 0
        assert [r["unary_p50_us"] > 0 for r in sequential["each_round"]] == [True], sequential
    assert re.search(
        r"^  unary Get p50 one at a time, gateway / bare server, each round: [\d.]+$", out, re.M
    ), out
    assert re.search(
        r"^  unary Gets/s with 8 in flight, gateway / bare server, each round: [\d.]+$", out, re.M
    )
    # Paced fan-out: every paced Set reached every subscriber on both servers.
    for server in ("baseline", "gateway"):
        paced = payload["results"][server]["paced"]
        assert paced["complete"] and paced["events"] + paced["conflated"] == paced["expected_events"], paced
    # The peers: each measured with every pattern (every Get answered, every value delivered), or skipped
    # with the reason printed; the gateway's figures are set against every one measured.
    measured = []
    for peer in PEERS:
        figures = payload["results"][peer]["peers"]
        assert "error" not in figures, (peer, figures)
        if "skipped" in figures:
            assert re.search(rf"^  {peer} +skipped: \S", out, re.MULTILINE), out
            continue
        measured.append(peer)
        for pattern in ("sequential", "unary"):
            assert figures[pattern]["errors"] == 0 and figures[pattern]["done"] == CALLS, (peer, figures)
        for pattern in ("listen", "paced"):
            fan = figures[pattern]
            assert fan["complete"] and fan["events"] == fan["expected_events"], (peer, pattern, fan)
        assert re.search(rf"^  {peer} +[\d,]+ +[\d,]+ +[\d,]+ +[\d,]+/[\d,]+ ", out, re.MULTILINE), out
    for row in payload["peer_ratios"]:
        assert sorted(row["gateway_over_peer"]) == measured, row
        if row["gateway"] is not None:
            assert all(ratio is not None and ratio > 0 for ratio in row["gateway_over_peer"].values()), row
    if measured:
        assert "(s) the gateway against the peers" in out, out
    # The line-protocol part: the same Gets straight to the device and through the gateway (unary and
    # Session), and over Session of the same property in-process (the floor), 1 and 8 in flight.
    for way in ("direct", "gateway", "gateway-session", "session-floor", "bare-session"):
        line = payload["results"][way]["line"]
        assert "error" not in line, (way, line)
        assert sorted(line["inflight"], key=int) == ["1", "8"]
        for figures in line["inflight"].values():
            assert figures["complete"] and figures["errors"] == 0, (way, figures)
    # Groups, find and registration ran at each of their sizes, on every member and entry.
    group = payload["results"]["in-process"]["group"]
    assert [d["members"] for d in group["sizes"]] == [100, 1000]
    assert all(d["accepted"] == d["members"] for d in group["sizes"]), group
    find = payload["results"]["in-process"]["find"]
    assert [d["entries"] for d in find["sizes"]] == [100, 1000]
    assert all(d["indexed"] == d["entries"] for d in find["sizes"]), find
    register = payload["results"]["gateway"]["register"]
    assert [d["members"] for d in register["sizes"]] == list(REGISTER_SIZES)
    for size in register["sizes"]:
        assert size["registered"] == size["members"] and size["last_member_answered"], (
            size["members"],
            size["registered"],
            size["first_errors"],
        )
    # The cost of mTLS and a token: both ways, both calls, every Get answered.
    tls = payload["results"]["gateway"]["tls"]
    for way in ("plaintext", "mtls-token"):
        for call in ("unary", "session"):
            assert tls[way][call]["errors"] == 0 and tls[way][call]["throughput_per_s"] > 0, (way, call)
    # Storage: both sizes, both calls, through the gateway and with plain file I/O.
    storage = payload["results"]["gateway"]["storage"]
    assert sorted(storage["sizes"]) == ["1k", "1m"] and storage["complete"], storage
    for figures in storage["sizes"].values():
        assert figures["get_ratio"] > 0 and figures["set_ratio"] > 0, figures
    # The state machine part ran every transition of its chart, each with its Set.
    machine = payload["results"]["in-process"]["statemachine"]
    assert machine["complete"] and machine["transitions"] == 2000, machine
    # The scheduler part decided at 100 and 1,000 entries, every request granted.
    scheduler = payload["results"]["in-process"]["scheduler"]
    assert [d["entries"] for d in scheduler["sizes"]] == [100, 1_000] and scheduler["complete"], scheduler
    # The camera part: ten Listeners counted frames, and a Get's frame decoded to 640x480.
    camera = payload["results"]["gateway"]["camera"]
    assert camera["complete"] and camera["listeners"] == 10 and camera["baseline"]["frames"] > 0, camera
    # The fusion part fused at 100 and 1,000 markers, every marker indexed, beside its baseline.
    fusion = payload["results"]["in-process"]["fusion"]
    assert [d["markers"] for d in fusion["sizes"]] == [100, 1_000] and fusion["complete"], fusion
    assert all(d["baseline_us"] > 0 and d["us_per_observation"] > 0 for d in fusion["sizes"]), fusion
    # The metrics part: pairs of batches on gateways with and without metrics, and the scrape saw the Gets.
    metrics = payload["results"]["gateway"]["metrics"]
    assert metrics["pairs"] >= 6 and len(metrics["pair_ratios"]) == metrics["pairs"], metrics
    assert metrics["scraped_get_calls"] >= metrics["pairs"] // 2 * metrics["calls_per_batch"], metrics
    # The cluster part: fan-out from 1, 2 and 4 gateway processes, every stream open to the end.
    cores = payload["results"]["cluster"]["cores"]
    assert [d["gateways"] for d in cores["sizes"]] == [1, 2, 4] and cores["complete"], cores
    assert all(d["events"] > 0 and d["streams_ended"] == 0 for d in cores["sizes"]), cores
    assert cores["usable_cores"] >= 1 and cores["judged_gateways"] in (2, 4), cores
    # The listener processes (Go where it builds, else Python, with a note) had their CPU measured too.
    assert cores["listener"] in ("go", "python") and cores["other_listeners"] == {}, cores
    assert (cores["listener"] == "python") == bool(cores["listener_notes"]), cores
    assert all(d["listener"] == cores["listener"] and d["listener_cores"] > 0 for d in cores["sizes"]), cores
    # The registry on etcd: every device registered, listed by every gateway, and after one gateway was
    # killed every one of its devices answered again through a survivor, none lost.
    if has_etcd:
        registry = payload["results"]["cluster"]["registry"]
        devices = CLUSTER_DEVICES
        assert registry["complete"] and registry["devices"] == devices and registry["gateways"] == 4, registry
        assert registry["listed_by_each"] == [devices] * 4 and registry["listed_after_failover"] == devices, (
            registry
        )
        assert registry["answered_again"] == registry["killed_gateway_devices"] == devices // 4, registry
        assert "(t) devices across gateways sharing a registry in etcd" in out, out
    titles = (
        "(e) Get of",
        "(f) group behaviors.moveto",
        "(g) registry find",
        "(h) members registered",
        "(i) the cost",
        "(j) storage",
        "(k) fan-out to",
        "(u) fan-out to",
        "(l) a chart",
        "(m) scheduler",
        "(o) camera",
        "(n) environment model",
        "(p) the cost of metrics",
        "(q) Get one at a time",
        "(r) Listen fan-out, paced",
        "(s) the peers",
        "(t) Listen fan-out from K gateway processes",
    )
    for title in titles:
        assert title in out, f"no table {title!r}:\n{out}"
    assert [t["name"] for t in payload["targets"]] == list(TARGETS)
