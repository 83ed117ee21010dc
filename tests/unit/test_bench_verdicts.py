"""How the benchmark judges the floors' targets and sets the gateway against its peers, on figures given.

No server runs here: the results are written out as the benchmark keeps
them, and the verdicts, the per-round judgement and the peer ratios are
read back from the benchmark's own report code.
"""

from __future__ import annotations

from typing import Any

import pytest

from bench.__main__ import _best
from bench.peer_ratios import compare
from bench.report import evaluate


def _sequential(**p50: float) -> dict[str, Any]:
    ways = {way: {"latency": {"p50_us": value, "p99_us": 2 * value}} for way, value in p50.items()}
    return {"ways": ways, **{f"{way}_p50_us": value for way, value in p50.items()}, "complete": True}


def _verdict(results: dict[str, Any], name: str) -> dict[str, Any]:
    return next(v for v in evaluate(results) if v["name"] == name)


@pytest.mark.parametrize(("session_p50", "verdict"), [(104.0, "PASS"), (106.0, "FAIL")])
def test_the_session_get_is_judged_against_the_bare_servers_echo(session_p50: float, verdict: str) -> None:
    results = {
        "baseline": {"sequential": _sequential(unary=300.0, session=110.0, echo=100.0)},
        "gateway": {"sequential": _sequential(unary=300.0, session=session_p50)},
    }
    judged = _verdict(results, "session-floor-p50")
    assert judged["figure"] == pytest.approx(session_p50 / 100.0)
    assert judged["verdict"] == verdict
    # p99 is held to twice the floor's p50: the gateway's p99 here is 2 × its own p50, just above.
    assert _verdict(results, "session-floor-p99")["verdict"] == "FAIL"


def test_the_unary_targets_hold_in_every_round_not_only_the_best() -> None:
    def rounds(*figures: float) -> list[dict[str, Any]]:
        return [{"throughput_per_s": f, "unary_p50_us": 1e6 / f, "latency": {}} for f in figures]

    # The gateway's best round beats the bare server's best; its second round is 20 % behind that round.
    gateway = {"unary": _best(rounds(1000.0, 800.0), "unary")}
    baseline = {"unary": _best(rounds(950.0, 1000.0), "unary")}
    assert gateway["unary"]["each_round"][1]["throughput_per_s"] == 800.0
    judged = _verdict({"gateway": gateway, "baseline": baseline}, "unary-inflight-rounds")
    assert judged["figure"] == pytest.approx(0.8)
    assert judged["verdict"] == "FAIL"
    # The earlier target reads the best rounds only, and passes.
    assert _verdict({"gateway": gateway, "baseline": baseline}, "unary-get")["verdict"] == "PASS"


def test_the_paced_part_keeps_the_round_of_lowest_latency() -> None:
    rounds = [{"latency": {"p50_us": 900.0}, "events_per_s": 5000.0}, {"latency": {"p50_us": 700.0}}]
    best = _best(rounds, "paced")
    assert best["best_round"] == 2
    assert best["rounds"] == [900.0, 700.0]


def test_the_proxy_target_allows_the_floor_plus_two_direct_round_trips() -> None:
    def line(p50: float) -> dict[str, Any]:
        return {"inflight": {"1": {"latency": {"p50_us": p50}}, "8": {"throughput_per_s": 1.0}}}

    results = {
        "baseline": {"sequential": _sequential(unary=300.0, session=110.0, echo=200.0)},
        "direct": {"line": line(70.0)},
        "gateway-session": {"line": line(340.0)},
    }
    judged = _verdict(results, "proxy-session-p50")
    assert judged["figure"] == pytest.approx(1.0)
    assert judged["verdict"] == "PASS"
    results["gateway-session"]["line"] = line(341.0)
    assert _verdict(results, "proxy-session-p50")["verdict"] == "FAIL"


def test_a_target_whose_part_did_not_run_is_not_judged() -> None:
    judged = _verdict({"gateway": {}}, "session-listen-memory")
    assert judged["figure"] is None
    assert judged["verdict"] == "NOT RUN (gateway memory_session)"


def test_the_gateway_is_set_against_each_peer_that_ran_and_not_against_one_skipped() -> None:
    peer = {
        "sequential": {"latency": {"p50_us": 200.0, "p99_us": 400.0}},
        "unary": {"throughput_per_s": 5000.0},
        "listen": {"events_per_s": 10_000.0},
        "paced": {"latency": {"p50_us": 1000.0}},
    }
    results = {
        "gateway": {
            "sequential": _sequential(unary=400.0, session=150.0),
            "listen": {"events_per_s": 20_000.0},
        },
        "opcua": {"peers": peer},
        "zenoh": {"peers": {"skipped": "eclipse-zenoh cannot be imported"}},
    }
    rows = {(row["figure"], row["way"]): row for row in compare(results)}
    unary = rows[("Get one at a time, p50 µs", "unary")]
    assert unary["gateway"] == 400.0 and unary["peers"] == {"opcua": 200.0}
    assert unary["gateway_over_peer"] == {"opcua": 2.0}
    assert rows[("fan-out, events/s", "one-by-one")]["gateway_over_peer"] == {"opcua": 2.0}
    # A figure the run did not measure on the gateway has no ratio.
    assert rows[("paced Set→delivery p50 µs", "Listen")]["gateway_over_peer"] == {"opcua": None}


def _line_way(inflight_8_per_s: float) -> dict[str, Any]:
    inflight = {"1": {"throughput_per_s": 1.0}, "8": {"throughput_per_s": inflight_8_per_s}}
    return {"line": {"inflight": inflight}}


@pytest.mark.parametrize(
    ("bare_per_s", "direct_per_s", "ceiling", "verdict"),
    [(20_000.0, 50_000.0, 20 / 70, "FAIL"), (60_000.0, 50_000.0, 60 / 110, "PASS")],
)
def test_the_proxied_paths_ceiling_is_grpcs_hop_and_the_device_in_turn(
    bare_per_s: float, direct_per_s: float, ceiling: float, verdict: str
) -> None:
    # A batch crosses both in turn: together f·d/(f+d) Gets/s, over the device's own d.
    results = {"bare-session": _line_way(bare_per_s), "direct": _line_way(direct_per_s)}
    judged = _verdict(results, "line-inflight-ceiling")
    assert judged["figure"] == pytest.approx(ceiling, abs=0.001)  # the verdict's figure is rounded
    assert judged["verdict"] == verdict
