"""The machine, the tables of absolute figures, the ratios against the targets, and the JSON file."""

from __future__ import annotations

import json
import math
import os
import platform
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, TextIO

import psutil  # type: ignore[import-untyped,unused-ignore]

#: results[server][part] is a part's ``as_dict()``, or {"error": "..."}.
Results = dict[str, dict[str, dict[str, Any]]]


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def version(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "not installed"

    return {
        "cpu_model": model,
        "logical_cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)),
        "memory_gib": round(psutil.virtual_memory().total / 2**30, 1),
        "os": f"{platform.system()} {platform.release()}",
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "grpcio": version("grpcio"),
        "protobuf": version("protobuf"),
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
    }


@dataclass(frozen=True)
class Target:
    """One target of the benchmark: a figure computed from the results, and its bound."""

    name: str
    description: str
    figure: Callable[[Results], float]
    #: "min": the figure must be at least ``bound``; "max": at most.
    kind: str
    bound: float
    unit: str
    needs: tuple[tuple[str, str], ...]


def _get(results: Results, server: str, part: str, key: str) -> float:
    return float(results[server][part][key])


TARGETS = (
    Target(
        "unary-get",
        "unary Get throughput, gateway / bare server",
        lambda r: (
            _get(r, "gateway", "unary", "throughput_per_s") / _get(r, "baseline", "unary", "throughput_per_s")
        ),
        "min",
        0.80,
        "x",
        (("gateway", "unary"), ("baseline", "unary")),
    ),
    Target(
        "session-get",
        "Gets over Session / unary Gets, both on the gateway",
        lambda r: (
            _get(r, "gateway", "session", "throughput_per_s")
            / _get(r, "gateway", "unary", "throughput_per_s")
        ),
        "min",
        3.0,
        "x",
        (("gateway", "session"), ("gateway", "unary")),
    ),
    Target(
        "listen-fanout",
        "Listen events/s, one-by-one, gateway / bare server",
        lambda r: (
            _get(r, "gateway", "listen", "events_per_s") / _get(r, "baseline", "listen", "events_per_s")
        ),
        "min",
        0.80,
        "x",
        (("gateway", "listen"), ("baseline", "listen")),
    ),
    Target(
        "listen-batched",
        "Listen events/s, bursts (gateway batches), gateway / bare server",
        lambda r: (
            _get(r, "gateway", "batched", "events_per_s") / _get(r, "baseline", "batched", "events_per_s")
        ),
        "min",
        3.0,
        "x",
        (("gateway", "batched"), ("baseline", "batched")),
    ),
    Target(
        "idle-listen-memory",
        "gateway RSS per idle Listen stream",
        lambda r: _get(r, "gateway", "memory", "per_stream_kib"),
        "max",
        16.0,
        "KiB",
        (("gateway", "memory"),),
    ),
)


def evaluate(results: Results) -> list[dict[str, Any]]:
    """Each target's figure, bound and verdict (PASS, FAIL, or why it could not be judged)."""
    verdicts = []
    for target in TARGETS:
        verdict: dict[str, Any] = {
            "name": target.name,
            "description": target.description,
            "bound": target.bound,
            "kind": target.kind,
            "unit": target.unit,
            "figure": None,
        }
        missing = [f"{s} {p}" for s, p in target.needs if p not in results.get(s, {})]
        failed = [f"{s} {p}" for s, p in target.needs if "error" in results.get(s, {}).get(p, {})]
        incomplete = [
            f"{s} {p}" for s, p in target.needs if results.get(s, {}).get(p, {}).get("complete") is False
        ]
        if missing:
            verdict["verdict"] = "NOT RUN (" + ", ".join(missing) + ")"
        elif failed:
            verdict["verdict"] = "FAIL (error in " + ", ".join(failed) + ")"
        else:
            try:
                figure = target.figure(results)
            except ZeroDivisionError:
                figure = math.nan
            verdict["figure"] = round(figure, 3)
            ok = figure >= target.bound if target.kind == "min" else figure <= target.bound
            verdict["verdict"] = "PASS" if ok else "FAIL"
            if incomplete:
                verdict["verdict"] += " (incomplete: " + ", ".join(incomplete) + ")"
        verdicts.append(verdict)
    return verdicts


def _fmt(value: Any, digits: int = 0) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return str(value)


def _table(out: TextIO, title: str, header: list[str], rows: list[list[str]]) -> None:
    full = [row for row in rows if len(row) == len(header)]
    widths = [max([len(h), *(len(r[i]) for r in full)]) for i, h in enumerate(header)]

    def line(cells: list[str]) -> str:
        return "  " + "  ".join(
            c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=False))
        )

    print(f"\n{title}", file=out)
    print(line(header), file=out)
    for row in rows:
        print(line(row) if len(row) == len(header) else "  " + "  ".join(row), file=out)


def _rows(results: Results, part: str, cells: Callable[[dict[str, Any]], list[str]]) -> list[list[str]]:
    rows = []
    for server, parts in results.items():
        if part not in parts:
            continue
        data = parts[part]
        if "error" in data:
            rows.append([server, "error: " + data["error"].splitlines()[0][:60]])
        else:
            rows.append([server, *cells(data)])
    return rows


def print_report(out: TextIO, info: dict[str, Any], results: Results, verdicts: list[dict[str, Any]]) -> None:
    """Print the machine, one table per part and the ratio lines."""
    print(
        f"machine: {info['cpu_model']}, {info['logical_cores']} cores ({info['usable_cores']} usable), "
        f"{info['memory_gib']} GiB; {info['os']}; {info['python']}; grpcio {info['grpcio']}; "
        f"protobuf {info['protobuf']}; load average at start {info['load_average_at_start']}",
        file=out,
    )

    def unary(d: dict[str, Any]) -> list[str]:
        lat, win = d["latency"], d["window"]
        return [
            f"{d['done']:,}",
            _fmt(d["throughput_per_s"]),
            _fmt(lat["p50_us"]),
            _fmt(lat["p99_us"]),
            _fmt(d["server_cpu_us_per_call"]),
            f"{win['server_busy']:.0%}",
            f"{win['client_busy']:.0%}",
            str(d["errors"]),
        ]

    rows = _rows(results, "unary", unary)
    if rows:
        first = next(
            iter(p["unary"] for p in results.values() if "unary" in p and "inflight" in p["unary"]), {}
        )
        _table(
            out,
            f"(a) unary Get, {first.get('inflight', '?')} calls in flight",
            [
                "server",
                "calls",
                "Gets/s",
                "p50 µs",
                "p99 µs",
                "srv CPU µs/call",
                "srv busy",
                "load busy",
                "errors",
            ],
            rows,
        )

    def session(d: dict[str, Any]) -> list[str]:
        lat, win = d["latency"], d["window"]
        return [
            f"{d['done']:,}",
            _fmt(d["throughput_per_s"]),
            _fmt(lat["p50_us"]),
            _fmt(lat["p99_us"]),
            _fmt(d["server_cpu_us_per_get"], 1),
            _fmt(d["replies_per_response"], 1),
            f"{win['server_busy']:.0%}",
            f"{win['client_busy']:.0%}",
            str(d["errors"]),
        ]

    rows = _rows(results, "session", session)
    if rows:
        first = next(iter(p["session"] for p in results.values() if "batch" in p.get("session", {})), {})
        _table(
            out,
            f"(b) Gets over Session, {first.get('batch', '?')} per message, "
            f"{first.get('window_batches', '?')} messages unanswered at most",
            [
                "server",
                "Gets",
                "Gets/s",
                "p50 µs",
                "p99 µs",
                "srv CPU µs/Get",
                "replies/msg",
                "srv busy",
                "load busy",
                "errors",
            ],
            rows,
        )

    def listen(d: dict[str, Any]) -> list[str]:
        lat, win = d["latency"], d["window"]
        return [
            f"{d['events']:,}/{d['expected_events']:,}",
            f"{d['conflated']:,}",
            _fmt(d["events_per_message"], 2),
            _fmt(d["events_per_s"]),
            _fmt(d["sets_per_s"]),
            _fmt(lat["p50_us"]),
            _fmt(lat["p99_us"]),
            _fmt(d["server_cpu_us_per_event"], 1),
            f"{win['server_busy']:.0%}",
            f"{win['client_busy']:.0%}",
        ]

    header = [
        "server",
        "events",
        "conflated",
        "events/msg",
        "events/s",
        "Sets/s",
        "p50 µs",
        "p99 µs",
        "srv CPU µs/event",
        "srv busy",
        "load busy",
    ]
    for part, label in (
        ("listen", "(c) Listen fan-out, one-by-one"),
        ("batched", "(c) Listen fan-out, batched"),
    ):
        rows = _rows(results, part, listen)
        if rows:
            first = next(iter(p[part] for p in results.values() if "subscribers" in p.get(part, {})), {})
            _table(
                out,
                f"{label}: {first.get('subscribers', '?')} subscribers on {first.get('properties', '?')} "
                f"propert{'y' if first.get('properties') == 1 else 'ies'}, {first.get('sets', '?')} Sets in "
                f"bursts of {first.get('burst', '?')}, {first.get('set_rate_per_s', '?')}",
                header,
                rows,
            )

    def memory(d: dict[str, Any]) -> list[str]:
        return [
            f"{d['opened']:,}",
            str(d["channels"]),
            _fmt(d["rss_before_mib"], 1),
            _fmt(d["rss_after_mib"], 1),
            _fmt(d["rss_after_close_mib"], 1),
            _fmt(d["per_stream_kib"], 1),
        ]

    rows = _rows(results, "memory", memory)
    rows += [
        [f"{row[0]} (Listens in Sessions)", *row[1:]] for row in _rows(results, "memory_session", memory)
    ]
    if rows:
        _table(
            out,
            "(d) idle Listen streams",
            [
                "server",
                "Listens",
                "channels",
                "RSS before MiB",
                "RSS open MiB",
                "RSS closed MiB",
                "KiB/stream",
            ],
            rows,
        )

    print("", file=out)
    for v in verdicts:
        sign = ">=" if v["kind"] == "min" else "<="
        figure = "n/a" if v["figure"] is None else f"{v['figure']:.2f} {v['unit']}"
        print(
            f"ratio {v['name']:<19} {figure:>10}   target {sign} {v['bound']:g} {v['unit']:<4} "
            f"{v['verdict']}   ({v['description']})",
            file=out,
        )


def save_json(path: str, payload: dict[str, Any]) -> None:
    """Write the whole run (machine, command, configuration, results, verdicts) to ``path``."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(payload, indent=2, allow_nan=True) + "\n")


def command_line() -> str:
    return " ".join([Path(sys.executable).name, "-m", "bench", *sys.argv[1:]])
