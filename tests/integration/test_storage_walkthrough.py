"""docs/storage.md's psctl examples, against the demo gateway's ``files``, on a busy machine.

The demo gateway runs in a folder of the test's own (its ``files`` service keeps ``./.demo-files``
there), and the page's lines run in one bash shell in that folder at a reader's pace, beside one
spinning process per core (tests/support/cpu_burner.py). The page's ``listen`` runs until Ctrl-C
while the reader edits the file; here it runs in the background for a bounded time while the shell
edits it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT
from support.walkthrough import command_lines, demo_gateway_in, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "storage.md").read_text(encoding="utf-8")
EDITED = "edited by hand"
#: One line of ``psctl listen files file``: its time, then the file's text.
EVENT = re.compile(r"^\d\d:\d\d:\d\d\.\d{3} files file = (.*)$")


@pytest.mark.timeout(240)
def test_the_storage_examples_do_what_the_page_says_on_a_busy_machine(tmp_path: Path) -> None:
    lines = command_lines(fenced_block(PAGE, "against the demo gateway, whose storage service is `files`"))
    assert len(lines) == 8 and lines[4].startswith("psctl listen files file")
    listen = lines[4]
    lines[4] = f"{listen} --duration 15 & sleep 6; printf '{EDITED}\\n' > .demo-files/notes/hello.txt; wait"
    photo = os.urandom(2048)
    (tmp_path / "a.jpg").write_bytes(photo)
    with demo_gateway_in(tmp_path) as gw, cpu_burners() as burners:
        ran = run_in_one_shell(lines, tmp_path, gw.address)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the examples ended"
    for step in ran:
        assert step.status == 0, f"$ {step.command}: {step.output}"
    _store, read, info, find, watched, _remove, put, get = ran
    assert put.output == [] and get.output == [], "a blob stored and written to a file prints nothing"
    assert read.output == ["hello, world"]
    assert re.fullmatch(r"<marker><name>notes/hello\.txt</name><size>12</size>.*</marker>", info.output[0])
    assert find.output == ["(notes/hello.txt)"]
    events = [m.group(1) for m in map(EVENT.match, watched.output) if m]
    assert events == ["hello, world", EDITED], watched.output
    assert not (tmp_path / ".demo-files" / "notes" / "hello.txt").exists(), "removed"
    assert (tmp_path / "copy.jpg").read_bytes() == photo, "its bytes as they are"
