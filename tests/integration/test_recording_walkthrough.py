"""docs/recording.md's psctl lines: a recording started, the swarm driven, listed and stopped, on
the demo gateway (in a folder of the test's own) and a busy machine (tests/support/cpu_burner.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT
from support.walkthrough import command_lines, demo_gateway_in, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "recording.md").read_text(encoding="utf-8")


@pytest.mark.timeout(240)
def test_a_recording_of_the_page_starts_lists_and_stops_on_a_busy_machine(tmp_path: Path) -> None:
    block = fenced_block(PAGE, "With psctl:", "sh")
    assert "# prints run1" in block
    lines = command_lines(block)
    with demo_gateway_in(tmp_path) as gw, cpu_burners() as burners:
        ran = run_in_one_shell(lines, tmp_path, gw.address)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the recording ended"
    for step in ran:
        assert step.status == 0, f"$ {step.command}: {step.output}"
    start, drive, listed, stop = ran
    assert start.output == ["run1"]
    assert drive.output == ["(rover1 rover2 scout1 scout2)"], "the swarm's members drive"
    [recording] = json.loads(listed.output[0])
    assert recording["name"] == "run1" and recording["state"] == "recording", recording
    assert recording["selectors"] == ["*/location", "scout1/*"] and recording["events"] > 0, recording
    assert stop.output == ["run1"]
    # The demo's recorder keeps its recordings in the files service's folder.
    mcap = tmp_path / ".demo-files" / "recordings" / recording["files"][0]
    assert mcap.read_bytes()[:8] == b"\x89MCAP0\r\n", "an MCAP file"
