"""Packages from npm for the tests that run third-party JavaScript (roslib, @foxglove/ws-protocol,
@mcap/core, buf, the Node.js client): ``npm ci`` in the package's folder, once per lock file.

After a successful install the lock file's hash is written into ``node_modules``; a later session
with the same lock file installs nothing. Where node or npm is missing, or the install fails (no
registry) or takes longer than :data:`NPM_TIMEOUT`, the test is skipped with a printed note saying
why — or fails, when ``required`` (a part every machine that runs the suite must have).
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from pathlib import Path
from typing import NoReturn

import pytest

#: The first install of a folder's packages may take a while; then it is stamped.
NPM_TIMEOUT = 300.0
#: Written into ``node_modules`` after a successful ``npm ci``: the hash of the lock file installed.
STAMP_NAME = ".installed-lock-sha256"


def _not_there(why: str, required: bool) -> NoReturn:
    if required:
        pytest.fail(why, pytrace=False)
    print(f"SKIPPED: {why}")
    pytest.skip(why)


def tool(name: str, what: str, *, required: bool = False) -> str:
    """The path of ``name`` (``node``, ``npm``) on PATH; ``what`` says which tests need it."""
    found = shutil.which(name)
    if found is None:
        _not_there(
            f"{what} need {name} on PATH: tests/run.sh installs it with apt-get (Debian nodejs, npm)",
            required,
        )
    return found


def npm_ci(folder: Path, what: str, *, required: bool = False, installed: Path | None = None) -> None:
    """Install ``folder``'s packages (its ``package-lock.json``) unless this lock file is installed
    already; ``installed``: a file the install must leave (checked too, so a half-removed
    ``node_modules`` is installed again)."""
    npm = tool("npm", what, required=required)
    lock = hashlib.sha256((folder / "package-lock.json").read_bytes()).hexdigest()
    stamp = folder / "node_modules" / STAMP_NAME
    if stamp.is_file() and stamp.read_text().strip() == lock and (installed is None or installed.is_file()):
        return
    try:
        done = subprocess.run(
            [npm, "ci", "--no-audit", "--no-fund"],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=NPM_TIMEOUT,
            check=False,
        )
    except subprocess.TimeoutExpired:
        _not_there(
            f"{what}: `npm ci` in {folder} took longer than {NPM_TIMEOUT:.0f} s (is the registry reachable?)",
            required,
        )
    if done.returncode != 0:
        output = f"{done.stdout[-800:]}\n{done.stderr[-2000:]}"
        _not_there(f"{what}: `npm ci` in {folder} failed (no registry?):\n{output}", required)
    stamp.write_text(lock + "\n")
