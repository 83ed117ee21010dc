"""docs/scale-out.md's walkthroughs, the page's own commands, on real etcd and a busy machine.

The page's one command (``python -m gateway.cluster --base-port 0``: every port a free one) starts
etcd, three gateways and six devices as it would for a reader; what it prints must be the page's
table, ports, process ids and the temporary folder aside. Then, as the reader does from another
shell, the page's lines run in one bash shell at a reader's pace (tests/support/walkthrough.py)
beside one spinning process per core (tests/support/cpu_burner.py), each gateway's address put
where the page has the one its table shows for that gateway:

* "Try it": any gateway answers for any device; a gateway killed (``kill -9`` its PID) while a
  client holding every gateway's address listens ("Clients: one list of gateways"): the command
  names it and prints who owns what without it, and the client's Listen goes on with one ``[gap]``;
* "Operating a cluster": the cluster view, a drain, an undrain and a rebalance read as the page
  shows them; then etcd stopped, and a registration refused read-only as the page shows it.

The cluster starts before the machine is made busy (a reader's cluster runs already when they
type the next command), so its start is bounded by what an idle machine takes. Without the
``etcd`` command the tests skip (tests/support/etcd.py). ``tests/integration/test_cluster_command.py``
holds the command's other promises (a port in use, no etcd, every process stopped).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from support.cluster_command import ClusterCommand
from support.cpu_burner import cpu_burners, spinning
from support.etcd import etcd_binary
from support.gateway_process import ROOT
from support.walkthrough import command_lines, console_steps, fenced_block, normalised, run_in_one_shell

pytestmark = [pytest.mark.slow]

PAGE = Path(ROOT, "docs", "scale-out.md").read_text(encoding="utf-8")
#: What differs between runs of the command: ports, process ids, its temporary folder, and the
#: columns' widths that follow from them.
VARYING = (
    (re.compile(r"127\.0\.0\.1:\d+"), "127.0.0.1:PORT"),
    (re.compile(r"\(logs in [^)]+\)"), "(logs in FOLDER)"),
    (re.compile(r"\(pid \d+\)"), "(pid PID)"),
    (re.compile(r"=\d+"), "=PID"),
    (re.compile(r"\s+"), " "),
)
#: What differs between runs of the cluster view besides: lease times, clock times, and the calls a
#: second each gateway answered (the view's own Gets among them).
VIEW_VARYING = (
    *VARYING,
    (re.compile(r"[+-]\d+(\.\d+)?s$"), "LEASE"),
    (re.compile(r"\b\d\d:\d\d:\d\d\b"), "TIME"),
    (re.compile(r"^(gw\d \S+ \S+ \S+ \S+ \d+) [\d.]+ "), r"\1 CALLS "),
)
#: A row of the command's gateway table: id, gRPC address, HTTP URL, line listener, devices owned.
GATEWAY_ROW = re.compile(r"^(gw\d)\s+(127\.0\.0\.1:\d+)\s+http://\S+/\s+(127\.0\.0\.1:\d+)\s+(.*)$")
#: A row of its device table: name, URL it is registered as, owner.
DEVICE_ROW = re.compile(r"^((?:thermo|rover)\d+)\s+(\S+)\s+(\S+|\(none yet\))$")
#: Seconds the failover Listen runs (until Ctrl-C on the page): the kill comes at LISTEN_KILL_AT,
#: the device is owned again within the lease (3 s) and a few seconds more on a busy machine.
LISTEN_S = 25
LISTEN_KILL_AT = 5
#: One event of ``psctl listen thermo5 data``: time, service, property, a number, and maybe how
#: many readings it stands for (a busy client reads the latest) and whether values were missed.
THERMO_EVENT = re.compile(r"^\d\d:\d\d:\d\d\.\d{3} thermo5 data = -?[\d.]+( \[conflated \d+\])?( \[gap\])?$")


def untagged_block(after: str) -> list[str]:
    """The lines of the first plain ``` block of the page after ``after`` (the command's output)."""
    return fenced_block(PAGE, after, "").splitlines()


def gateway_addresses(lines: list[str]) -> dict[str, str]:
    """Gateway id → its gRPC address, from the rows of a table of gateways."""
    rows = (re.match(r"^(gw\d)\s+(127\.0\.0\.1:\d+)\s", line) for line in lines)
    return {m.group(1): m.group(2) for m in rows if m}


def with_addresses(command: str, page: dict[str, str], actual: dict[str, str]) -> str:
    """``command`` with each gateway's address on the page replaced by that gateway's address here."""
    for gateway, address in page.items():
        command = command.replace(address, actual[gateway])
    return command


def shown_pattern(line: str) -> re.Pattern[str]:
    """A line the page shows, as a pattern: its ``...`` stands for whatever the run printed there."""
    return re.compile(".*".join(re.escape(part) for part in line.split("...")))


def start_the_pages_cluster(tmp_path: Path) -> ClusterCommand:
    """The page's command with free ports, in ``tmp_path``, once it says it is ready."""
    etcd_binary()  # skips, saying why, without etcd
    lines = command_lines(fenced_block(PAGE, "## Try it: one command"))
    assert lines == ["python -m gateway.cluster", "python -m gateway.cluster --base-port 0"]
    command = ClusterCommand(shlex.split(lines[1])[3:], cwd=tmp_path)
    command.wait_for("cluster ready")
    return command


@pytest.mark.timeout(240)
def test_the_one_command_cluster_answers_anywhere_and_outlives_a_killed_gateway(tmp_path: Path) -> None:
    shown = untagged_block("`--keep` keeps it):")
    command = start_the_pages_cluster(tmp_path)
    try:
        started = command.lines[: command.wait_for("cluster ready") + 1]
        # What it printed is the page's table; the page cuts the processes line short ("...").
        assert shown[-2].endswith(" ...") and len(started) == len(shown), "\n".join(started)
        expected = normalised(shown, VARYING)
        printed = normalised(started, VARYING)
        assert printed[-2].startswith(expected[-2].removesuffix(" ...")), printed[-2]
        assert printed[:-2] + printed[-1:] == expected[:-2] + expected[-1:]
        page_addresses, addresses = gateway_addresses(shown), gateway_addresses(started)
        registered = {m.group(1): m.group(2) for m in map(DEVICE_ROW.match, started) if m}
        owners = {m.group(1): m.group(3) for m in map(DEVICE_ROW.match, started) if m}
        pids = command.pids()

        killed = untagged_block("without the dead gateway:")
        victim = re.match(r"^(gw\d) \(pid (\d+)\) exited with status -9", killed[0])
        assert victim is not None, killed[0]
        dead = victim.group(1)
        # The client of "Clients: one list of gateways" lists gw-a first: gw-a is the gateway killed.
        client = command_lines(fenced_block(PAGE, "then values again\n```\n", ""))
        assert client == ["psctl -t gw-a:50051,gw-b:50051,gw-c:50051 listen thermo5 data --resume"]
        survivors = sorted(set(addresses) - {dead})
        listen = client[0]
        for placeholder, gateway in zip(
            ("gw-a:50051", "gw-b:50051", "gw-c:50051"), [dead, *survivors], strict=True
        ):
            listen = listen.replace(placeholder, addresses[gateway])
        failover = f"{listen} --duration {LISTEN_S} & sleep {LISTEN_KILL_AT}; kill -9 {pids[dead]}; wait"

        lines = command_lines(
            fenced_block(PAGE, "Then, from another shell, any gateway answers for any device:")
        )
        assert len(lines) == 3 and lines[2].startswith("psctl --target ")
        commands = [with_addresses(line, page_addresses, addresses) for line in lines]
        commands[2] += " --duration 3"  # it runs until Ctrl-C on the page
        printed_before_kill = len(command.lines)
        with cpu_burners() as burners:
            ran = run_in_one_shell([*commands, failover], tmp_path)
            after = command.wait_for(" (pid ", within=60, after=printed_before_kill)
            table_end = command.wait_for(
                "thermo5 ",
                within=60,
                after=command.wait_for("device ", after=after, at_start=True),
                at_start=True,
            )
            assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"
        for step in ran:
            assert step.status == 0, f"$ {step.command}: {step.output}"
        forwarded, owner, states, failed_over = ran
        # thermo1 is owned by gw1 and read through gw2: forwarded.
        assert owners["thermo1"] == "gw1" and re.fullmatch(r"-?\d+(\.\d+)?", forwarded.output[0]), (
            forwarded.output
        )
        assert owner.output == ["gw1"]
        state_lines = {line.split(" ", 1)[1] for line in states.output}
        for name in [*owners, "registry"]:
            assert f"registry services.{name}.state = up" in state_lines, states.output

        # The client's Listen went on through the next gateway, with one [gap], then values again.
        events = [line for line in failed_over.output if THERMO_EVENT.match(line)]
        notes = [line for line in failed_over.output if not THERMO_EVENT.match(line)]
        gaps = [i for i, line in enumerate(events) if line.endswith(" [gap]")]
        assert len(gaps) == 1 and 0 < gaps[0] < len(events) - 1, failed_over.output
        assert all(line.startswith("listen thermo5 data: ") and "resuming at" in line for line in notes), (
            notes
        )

        # The command named the gateway killed, waited, and printed who owns what without it.
        story = command.lines[after : table_end + 1]
        assert normalised(story[:1], VARYING) == normalised(killed[:1], VARYING)
        assert killed[1] == "    ..." and killed[-1] == "..."
        waiting = next(i for i, line in enumerate(story[1:], 1) if not line.startswith("    "))
        assert waiting > 1, "the last lines of its log, indented"
        expected_rest = normalised(killed[2:5], VARYING)
        assert normalised(story[waiting : waiting + 3], VARYING) == expected_rest
        page_after = {m.group(1): set(m.group(4).split(", ")) for m in map(GATEWAY_ROW.match, killed) if m}
        now = {m.group(1): set(m.group(4).split(", ")) for m in map(GATEWAY_ROW.match, story) if m}
        assert sorted(now) == survivors == sorted(page_after)
        # A device that had dialled in to the dead gateway is with whichever survivor it reached
        # first once the lease was over: the page's is one of them, and so is this run's, unless
        # (a busy machine) it has not dialled in again yet.
        redialled = {
            name for name, owner in owners.items() if owner == dead and registered[name].startswith("tcp-in:")
        }
        assert redialled, registered
        owners_now = {m.group(1): m.group(3) for m in map(DEVICE_ROW.match, story) if m}
        for name in redialled:
            assert sum(name in devices for devices in page_after.values()) == 1, (name, page_after)
            with_one = sum(name in devices for devices in now.values()) == 1
            assert with_one or owners_now[name] == "(none yet)", story
        assert {g: d - redialled for g, d in now.items()} == {g: d - redialled for g, d in page_after.items()}
    finally:
        status = command.stop()
    assert status == 0, "\n".join(command.lines)


@pytest.mark.timeout(240)
def test_the_cluster_view_a_drain_and_read_only_mode_read_as_the_page_shows(tmp_path: Path) -> None:
    view = console_steps(fenced_block(PAGE, "asked through `gw2`:", "console"))
    assert [c.split()[3:] for c, _ in view] == [
        ["cluster", "--devices"],
        ["cluster", "drain", "gw1"],
        ["cluster", "--devices"],
        ["cluster", "undrain", "gw1"],
        ["cluster", "rebalance"],
    ]
    read_only = console_steps(fenced_block(PAGE, "What needs etcd is refused with UNAVAILABLE", "console"))
    assert len(read_only) == 1 and read_only[0][1][0].startswith("error: UNAVAILABLE")
    command = start_the_pages_cluster(tmp_path)
    try:
        addresses = gateway_addresses(command.lines)
        # The page's view was asked of gw2 at the address its own table shows; the registration,
        # of gw2 at the address the first table shows.
        view_addresses = gateway_addresses(view[0][1])
        first_addresses = gateway_addresses(untagged_block("`--keep` keeps it):"))
        commands = [with_addresses(c, view_addresses, addresses) for c, _ in view]
        # "To watch read-only mode, stop etcd (`kill` its PID from the `processes:` line)".
        commands += [
            f"kill {command.pids()['etcd']}",
            with_addresses(read_only[0][0], first_addresses, addresses),
        ]
        with cpu_burners() as burners:
            ran = run_in_one_shell(commands, tmp_path)
            assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"
    finally:
        status = command.stop()
    assert status == 0, "\n".join(command.lines)
    for (shown_command, expected), step in zip(view, ran, strict=False):
        assert step.status == 0, f"$ {shown_command}: {step.output}"
        assert normalised(step.output, VIEW_VARYING) == normalised(expected, VIEW_VARYING), (
            f"$ {shown_command}"
        )
    stopped_etcd, registration = ran[len(view) :]
    assert stopped_etcd.status == 0, stopped_etcd.output
    assert registration.status != 0
    [refused] = normalised(registration.output, VARYING)
    [shown] = normalised(read_only[0][1], VARYING)
    assert shown_pattern(shown).fullmatch(refused), refused
