"""Containers and networks of a test run, labelled with its PID, and their removal.

A container left running keeps its published port forwarded: every later connection to
127.0.0.1 on that port, whoever listens there, is sent to the dead container. So everything
the container tests create carries ``RUN_LABEL``, and what a killed run left is removed by the
next one.
"""

from __future__ import annotations

import os
import re
import subprocess

#: The label on every container and network these tests create: the PID of the test process.
RUN_LABEL = "io.psgateway.test-run"


#: How a listing names each container or network: its id and its labels (``map[key:value ...]``).
FORMAT = "{{.ID}} {{.Labels}}"


def run_labels() -> dict[str, str]:
    """The labels for a container or network this test process creates."""
    return {RUN_LABEL: str(os.getpid())}


def _alive(pid: str) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def remove_labelled(podman_env: dict[str, str], *, run: str | None) -> list[str]:
    """Remove the containers, then the networks, labelled by test run ``run`` (None: by runs that are gone).

    Returns what was removed, as ``kind name``.
    """
    removed: list[str] = []
    for kind, listing, removal in (
        ("container", ["ps", "-a"], ["rm", "-f"]),
        ("network", ["network", "ls"], ["network", "rm", "-f"]),
    ):
        listed = subprocess.run(
            ["podman", *listing, "--filter", f"label={RUN_LABEL}", "--format", FORMAT],
            env=podman_env, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        for line in listed.stdout.splitlines():
            ident, _, labels = line.strip().partition(" ")
            found = re.search(rf"\b{re.escape(RUN_LABEL)}:(\d+)", labels)
            owner = found.group(1) if found else ""
            if ident and (owner == run if run is not None else not _alive(owner)):
                subprocess.run(
                    ["podman", *removal, ident], env=podman_env, capture_output=True, timeout=60, check=False
                )
                removed.append(f"{kind} {ident}")
    return removed
