"""Without Chromium or its driver the browser tests skip, and the skip names what is missing."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from console_support import CHROMEDRIVER, CHROMIUM, ROOT, missing_browser


def test_a_missing_chromium_or_driver_is_named(tmp_path: Path) -> None:
    absent = tmp_path / "chromium"
    reason = missing_browser(absent, CHROMEDRIVER)
    assert reason is not None
    assert str(absent) in reason
    assert "apt-get install chromium chromium-driver" in reason
    not_executable = tmp_path / "chromedriver"
    not_executable.write_text("")
    reason = missing_browser(CHROMIUM, not_executable)
    assert reason is not None
    assert str(not_executable) in reason


def test_the_browser_tests_skip_saying_why(tmp_path: Path) -> None:
    """A pytest run of the browser tests with no driver: every one skips, and the reason is shown."""
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-m", "browser", "tests/browser"],
        cwd=ROOT,
        env={**os.environ, "PS_CHROMEDRIVER": str(tmp_path / "no-chromedriver")},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "passed" not in done.stdout and "failed" not in done.stdout, done.stdout
    assert f"browser tests skipped: {tmp_path / 'no-chromedriver'} missing" in done.stdout, done.stdout
