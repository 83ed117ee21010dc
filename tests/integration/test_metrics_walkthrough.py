"""docs/metrics.md against real gateway processes: its scrape, run as a reader runs it on a busy machine
(one spinning process per core, tests/support/cpu_burner.py), and its tables of metrics, labels and
label values, held against what a gateway serving devices exposes.
"""

from __future__ import annotations

import re
import shlex
import shutil
import sys
import urllib.request
from pathlib import Path

import grpc
import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.walkthrough import console_steps, demo_gateway_in, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "metrics.md").read_text(encoding="utf-8")
#: A line of the exposition: a sample's name, its labels (if any) and its value.
SAMPLE = re.compile(r"^(\w+)(?:\{(.*)\})? \S+$")
LABEL = re.compile(r'(\w+)="([^"]*)"')


def section(title: str) -> str:
    """The page's text under ``## TITLE``, up to the next ``## `` heading."""
    return PAGE.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def table_rows(text: str) -> list[list[str]]:
    """The cells of every table row in ``text`` (header and rule rows left out)."""
    rows = [[cell.strip() for cell in line.strip().strip("|").split("|")] for line in text.splitlines()]
    headers = ("metric", "label")
    return [row for row in rows if len(row) > 1 and not set(row[0]) <= set("-") and row[0] not in headers]


def ticked(cell: str) -> list[str]:
    """The `backticked` words of a table cell, outside its parentheses."""
    return re.findall(r"`([^`]+)`", re.sub(r"\([^)]*\)", "", cell))


@pytest.mark.timeout(120)
def test_a_scrape_of_a_gateway_just_started_prints_what_the_page_shows_on_a_busy_machine(
    tmp_path: Path,
) -> None:
    if shutil.which("curl") is None:
        pytest.skip("curl is not installed (Debian package curl)")
    steps = console_steps(fenced_block(PAGE, "On a gateway just started", "console"))
    assert [command.split()[0] for command, _ in steps] == ["psgateway", "curl"]
    (serve, _), (scrape, shown) = steps
    # site.toml as the serve line's comment describes it, on a port from the OS.
    http = re.search(r'# with \[http\] listen = "(127\.0\.0\.1:8080)"$', serve)
    assert http is not None, serve
    (tmp_path / "site.toml").write_text('[http]\nlisten = "127.0.0.1:0"\n')
    args = shlex.split(serve.split("#", 1)[0].strip().removesuffix("&"))[1:]
    gw = GatewayProcess(
        [sys.executable, "-m", "gateway.cli", *args, "--listen", "127.0.0.1:0"],
        {"PYTHONPATH": str(ROOT)},  # run in the reader's folder: this checkout's packages
        cwd=tmp_path,
    )
    try:
        gw.wait_ready(30)
        with cpu_burners() as burners:
            [ran] = run_in_one_shell([scrape.replace(http.group(1), gw.http_address)], tmp_path)
            assert all(spinning(pid) for pid in burners), "the machine was busy until the scrape ended"
    finally:
        gw.stop()
    assert ran.status == 0 and ran.output == shown, ran.output


def exposed(url: str) -> tuple[dict[str, str], dict[str, dict[str, set[str]]]]:
    """The type of every metric family at ``url``, and each family's labels with the values seen."""
    with urllib.request.urlopen(url, timeout=30) as response:
        text = response.read().decode()
    types = dict(re.findall(r"^# TYPE (\w+) (\w+)$", text, re.M))
    labels: dict[str, dict[str, set[str]]] = {name: {} for name in types}
    for line in text.splitlines():
        sample = SAMPLE.match(line)
        if line.startswith("#") or sample is None:
            continue
        name = sample.group(1)
        family = name if name in types else re.sub(r"_(bucket|sum|count)$", "", name)
        assert family in types, f"a sample of no family: {line}"
        for label, value in LABEL.findall(sample.group(2) or ""):
            if label != "le":  # a histogram's buckets
                labels[family].setdefault(label, set()).add(value)
    return types, labels


@pytest.mark.timeout(120)
def test_a_gateway_with_devices_exposes_every_metric_the_page_lists_and_no_other(tmp_path: Path) -> None:
    documented = {ticked(row[0])[0]: row for row in table_rows(section("Every metric"))}
    assert len(documented) >= 20 and "psgateway_grpc_calls_total" in documented
    bounds = {
        label: row for row in table_rows(section("Labels and their bounds")) for label in ticked(row[0])
    }
    with demo_gateway_in(tmp_path) as gw:  # the demo: sim robots, devices on TCP and on a pty
        with grpc.insecure_channel(gw.address) as channel:
            grpc.channel_ready_future(channel).result(timeout=30)
        exposed(f"{gw.http_url}metrics")  # an HTTP request answered: its series show in the next scrape
        types, labels = exposed(f"{gw.http_url}metrics")
    assert sorted(types) == sorted(documented), "the page lists exactly the metrics a gateway exposes"
    for name, (_, kind, label_cell, _) in documented.items():
        assert types[name] == kind, name
        assert sorted(labels[name]) == sorted(ticked(label_cell)), f"{name}: {labels[name]}"
        for label, seen in labels[name].items():
            allowed = set(ticked(bounds[label][1]))
            if label == "code":
                allowed = {code.name for code in grpc.StatusCode}
            elif label == "route":
                route = re.compile(r"(GET|PUT|POST|DELETE) /\S*|unrouted")
                assert all(route.fullmatch(value) for value in seen), seen
                continue
            elif label == "status":
                assert all(re.fullmatch(r"\d{3}", value) for value in seen), seen
                continue
            assert seen <= allowed, f"{name} {label}: {seen - allowed} not on the page"
    # The labels whose every value shows from the start: exactly the page's.
    assert labels["psgateway_grpc_calls_total"]["method"] == set(ticked(bounds["method"][1]))
    assert labels["psgateway_session_requests_total"]["call"] == set(ticked(bounds["call"][1]))
    assert labels["psgateway_open_streams"]["kind"] == set(ticked(bounds["kind"][1]))
    assert labels["psgateway_devices"]["transport"] == {"tcp", "serial"}, "the demo's devices"
    assert labels["psgateway_http_requests_total"] == {"route": {"GET /metrics"}, "status": {"200"}}, (
        "the first scrape is counted (`/metrics` included)"
    )
