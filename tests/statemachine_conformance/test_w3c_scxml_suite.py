"""The State Machine Service against the W3C SCXML IRP tests (mandatory and optional sets).

The charts come from python-statemachine's sdist on PyPI at test time (see
tests/support/w3c_scxml.py); the test skips, saying why, when PyPI cannot be reached.
Every chart's outcome is compared with ``expected.txt``: a chart that did better than the
list says fails too, asking for the list to be updated, so the table in
docs/statemachine.md stays true. ``SCXML_W3C_UPDATE=1`` rewrites the list from this run.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from support.w3c_scxml import (
    BY_DESIGN,
    PINNED,
    ROOT,
    Outcome,
    charts,
    counts,
    fetch_suite,
    read_expected,
    run_suite,
    write_expected,
)

EXPECTED = Path(__file__).with_name("expected.txt")
HEADER = f"""\
# The outcome of each W3C SCXML IRP chart (python-statemachine {PINNED}'s copies) in the State
# Machine Service: pass, refused FEATURE (left out by design: docs/statemachine.md), or fail REASON.
# Written by SCXML_W3C_UPDATE=1 pytest tests/statemachine_conformance/test_w3c_scxml_suite.py"""


async def test_every_w3c_chart_ends_as_the_checked_in_list_says() -> None:
    folder = fetch_suite()
    if isinstance(folder, str):
        pytest.skip(folder)
    texts = charts(folder)
    outcomes = await run_suite(texts)
    for kind in ("mandatory", "optional"):
        tally = counts(outcomes, kind)
        runnable = tally["pass"] + tally["fail"]
        print(f"{kind}: {tally} ({tally['pass']} of {runnable} not refused by design pass)")
    if os.environ.get("SCXML_W3C_UPDATE") == "1":
        write_expected(EXPECTED, outcomes, HEADER)
    expected = read_expected(EXPECTED)
    worse: list[str] = []
    changed: list[str] = []
    for key, outcome in sorted(outcomes.items()):
        listed = expected.get(key, Outcome("fail", "not in the list"))
        if not outcome.same_as(listed):
            line = f"{key}: listed {listed}, now {outcome}"
            (worse if listed.kind == "pass" or outcome.kind == "fail" else changed).append(line)
    assert not worse, "charts that do worse than expected.txt says:\n" + "\n".join(worse)
    assert not changed, (
        "charts that do better, or are refused for another feature: update expected.txt "
        "(SCXML_W3C_UPDATE=1) and the table in docs/statemachine.md:\n" + "\n".join(changed)
    )
    assert set(expected) == set(outcomes), "expected.txt names charts the suite does not have"


def test_every_feature_refused_by_design_is_listed_in_the_docs() -> None:
    docs = (ROOT / "docs" / "statemachine.md").read_text(encoding="utf-8")
    listed = {o.detail for o in read_expected(EXPECTED).values() if o.kind == "refused"}
    for feature in sorted(listed):
        assert feature in BY_DESIGN, f"{feature} is refused but not among the features left out by design"
        assert re.search(rf"`{re.escape(feature)}`", docs), f"docs/statemachine.md does not list `{feature}`"
