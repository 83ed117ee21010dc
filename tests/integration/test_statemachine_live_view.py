"""A Listen on a machine's ``state`` through a real gateway process: every stable configuration.

``M.state`` is the configuration at the end of each macrostep (W3C SCXML): a chart driven
through many macrosteps in quick succession shows each of them, in order, none conflated, to a
reader that keeps up; the configurations passed through inside a macrostep (eventless
transitions, internal events) are not shown, and ``M.log`` has every transition. The chain
example of docs/statemachine.md runs as a user types it, with ``psctl``.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.waiting import eventually

from clients.aio import AsyncClient

CONFIG = """
[[services]]
name = "missions"
type = "statemachine"
"""

#: Stops n0 .. n{STOPS-1}; from each, the event `next` goes to a hop that moves on to the next
#: stop without an event, and the stop raises `arrived`, handled inside the same macrostep.
STOPS = 40


def ladder(stops: int) -> str:
    states = []
    for i in range(stops):
        last = i + 1 == stops
        following = "n0" if last else f"hop{i}"
        states.append(
            f'<state id="n{i}"><onentry><raise event="arrived"/></onentry>'
            '<transition event="arrived" type="internal">'
            '<assign location="seen" expr="seen + 1"/></transition>'
            f'<transition event="next" target="{following}"/></state>'
        )
        if not last:
            states.append(f'<state id="hop{i}"><transition target="n{i + 1}"/></state>')
    return (
        '<scxml xmlns="http://www.w3.org/2005/07/scxml" initial="n0">'
        '<datamodel><data id="seen" expr="0"/></datamodel>' + "".join(states) + "</scxml>"
    )


@pytest.mark.timeout(90)
async def test_a_state_listen_shows_every_stable_configuration_in_order_and_the_log_every_transition(
    gateway_process: Any,
) -> None:
    gw = gateway_process(CONFIG)
    async with AsyncClient(gw.address) as client:
        await client.set("missions", "ladder.definition", ladder(STOPS))
        seen: list[str] = []
        conflated = 0
        last = f"(n{STOPS - 1})"

        async def watch() -> None:
            nonlocal conflated
            async for event in client.listen("missions", "ladder.state"):
                seen.append(event.value)
                conflated += event.conflated
                if event.value == last:
                    return

        watcher = asyncio.create_task(watch())
        await eventually(lambda: asyncio.sleep(0, seen), lambda s: s == ["()"], what="the first value")
        await client.set("missions", "ladder.start", "")
        await eventually(lambda: asyncio.sleep(0, seen), lambda s: s[-1:] == ["(n0)"], what="(n0)")
        # One macrostep per event, sent as fast as the gateway answers each Set.
        for _ in range(STOPS - 1):
            await client.set("missions", "ladder.events", "next")
        await asyncio.wait_for(watcher, 30)

        assert seen == ["()", *(f"(n{i})" for i in range(STOPS))]
        assert conflated == 0
        assert not any(value.startswith("(hop") for value in seen)
        lines = [line.split(" ", 1)[1] for line in (await client.get("missions", "ladder.log")).splitlines()]
        moves = [line for line in lines if " -> " in line]
        expected = ["() -> n0"]
        for i in range(STOPS - 1):
            expected += [f"n{i} -> hop{i} on next", f"hop{i} -> n{i + 1}"]
        assert moves == expected, moves[:5]


def docs_chain_example() -> tuple[str, list[str]]:
    """The chart and the commands of the chain example in docs/statemachine.md."""
    page = Path(ROOT, "docs", "statemachine.md").read_text(encoding="utf-8")
    section = page.split("An example, `chain.scxml`:", 1)[1]
    chart = section.split("```xml\n", 1)[1].split("```", 1)[0]
    commands = section.split("```bash\n", 1)[1].split("```", 1)[0].strip().splitlines()
    return chart, commands


@pytest.mark.timeout(90)
def test_the_chain_example_of_the_docs_shows_s0_then_c_and_logs_a_and_b(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    chart, commands = docs_chain_example()
    (tmp_path / "chain.scxml").write_text(chart, encoding="utf-8")
    # The demo gateway, whose state machine service is `missions`, in the test's folder: the chart
    # it stores in `files` stays there, and no later demo loads it.
    gw = fresh_demo_gateway
    script = "\n".join(
        [f'psctl() {{ "{sys.executable}" -m clients.cli "$@"; }}', "set -e", *commands, "wait"]
    )
    env = {**os.environ, "PSCTL_TARGET": gw.address, "PYTHONPATH": str(ROOT)}
    # As a reader runs it: on a machine busy with other work, where each psctl takes a second or two.
    with cpu_burners() as burners:
        done = subprocess.run(
            ["bash", "-c", script],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert all(spinning(pid) for pid in burners), "the machine was busy until the example ended"
    assert done.returncode == 0, done.stderr
    events = [line for line in done.stdout.splitlines() if " missions chain.state = " in line]
    assert [line.split(" = ", 1)[1] for line in events] == ["(s0)", "(c)"], done.stdout
    log = [line.split(" ", 1)[1] for line in done.stdout.splitlines() if " -> " in line]
    assert log == ["() -> s0", "s0 -> a on go", "a -> b", "b -> c on next"], done.stdout
