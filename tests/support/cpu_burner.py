"""A machine kept busy: one spinning child process per core, beside a test.

The docs' walkthroughs are read by people whose machines are busy with other work, where every
``psctl`` call takes a second or two to start. A walkthrough test that passes only on an idle
machine says nothing about what those readers see, so these tests run beside :func:`cpu_burners`,
from when the gateway is ready (a reader's gateway runs already when the walkthrough begins)::

    def test_the_page_runs_as_written(gateway_process):
        target = gateway_process().address
        with cpu_burners() as burners:
            ...  # the page's commands
            assert all(spinning(pid) for pid in burners)

Each burner is a child process that spins until its own deadline (so one outlives neither its
``limit`` nor a test run that was killed), and is ended by its PID when the block ends.
``PS_TEST_BURNERS`` sets how many (``0``: none, for a run that must not load a shared machine);
one per core by default, less one per other test worker beside this one (:func:`burner_count`).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

#: Seconds a burner spins at most, whatever happens to the test that started it: longer than any
#: walkthrough test's own time limit.
DEFAULT_LIMIT = 300.0
#: The loop each burner runs: busy until its deadline, then it exits by itself.
_SPIN = "\n".join(
    [
        "import sys, time",
        "end = time.monotonic() + float(sys.argv[1])",
        "while time.monotonic() < end:",
        "    pass",
    ]
)


def burner_count() -> int:
    """How many burners a busy machine gets: ``PS_TEST_BURNERS``, else one per core less one per
    other test worker running beside this one (pytest-xdist's ``PYTEST_XDIST_WORKER_COUNT``: the
    suite's other worker keeps a core busy already, and a burner beside it would slow its tests, not
    this walkthrough's reader), at least one."""
    configured = os.environ.get("PS_TEST_BURNERS", "").strip()
    if configured:
        return max(0, min(int(configured), 64))
    others = max(0, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1) - 1)
    return max(1, (os.cpu_count() or 1) - others)


@contextmanager
def cpu_burners(count: int | None = None, limit: float = DEFAULT_LIMIT) -> Iterator[list[int]]:
    """Run ``count`` spinning processes (default :func:`burner_count`) for the block; their PIDs.

    Each stops by itself after ``limit`` seconds; the rest are killed by PID when the block ends."""
    burners: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(burner_count() if count is None else count):
            burners.append(
                subprocess.Popen(
                    [sys.executable, "-c", _SPIN, str(limit)],
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        yield [burner.pid for burner in burners]
    finally:
        for burner in burners:
            if burner.poll() is None:
                burner.kill()
        for burner in burners:
            burner.wait(10)


def spinning(pid: int) -> bool:
    """Whether process ``pid`` is alive and not a zombie (Linux: its state in ``/proc``)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            state = stat.read().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state not in ("Z", "X")
