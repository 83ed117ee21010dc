"""The busy machine the walkthrough tests run on: its burners spin while the block runs, and none is
left behind, whether the block ends or a burner's own limit does."""

from __future__ import annotations

import time

from support.cpu_burner import cpu_burners, spinning


def test_burners_spin_during_the_block_and_are_gone_after_it() -> None:
    with cpu_burners(2) as pids:
        assert len(pids) == 2
        assert all(spinning(pid) for pid in pids)
    assert not any(spinning(pid) for pid in pids)


def test_a_burner_stops_by_itself_at_its_limit() -> None:
    with cpu_burners(1, limit=0.5) as pids:
        deadline = time.monotonic() + 30.0
        while spinning(pids[0]) and time.monotonic() < deadline:
            time.sleep(0.1)
        # Ended by itself, but not yet reaped (the block reaps it): a zombie is not spinning.
        assert not spinning(pids[0])
