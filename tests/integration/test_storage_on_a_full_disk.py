"""A store on a full disk: refused as RESOURCE_EXHAUSTED, and the file it would have replaced is kept.

The disk is a real one, a 256 KiB tmpfs mounted in a user namespace of its own (``unshare -rm``),
with the storage service's :class:`~services.apps.storage.disk.Folder` writing to it in a child
process; where user namespaces or unshare are missing, the test skips saying why.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# A child Python process in a namespace of its own, and a mount: a second, not milliseconds.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]

_FULL_DISK = textwrap.dedent(
    """
    import os, subprocess, sys
    from pathlib import Path
    from services.kernel.errors import ResourceExhausted
    from services.apps.storage.disk import Folder
    root = Path(sys.argv[1])
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(root)], check=True)
    folder = Folder(root)
    folder.write("kept.txt", b"the old content")
    try:
        folder.write("kept.txt", b"x" * 1024 * 1024)
    except ResourceExhausted as e:
        print("REFUSED", e.message)
    print("CONTENT", folder.read("kept.txt", 100).decode())
    print("FILES", sorted(os.listdir(root)))
    """
)


def test_a_full_disk_is_resource_exhausted_and_changes_nothing(tmp_path: Path) -> None:
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("a full disk needs a tiny tmpfs: unshare (util-linux) is not installed")
    mount_point = tmp_path / "small"
    mount_point.mkdir()
    probe = subprocess.run(
        [unshare, "-rm", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {mount_point}"],
        capture_output=True,
        text=True,
        check=False,
    )
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a tiny tmpfs in a user namespace here: {probe.stderr.strip()}")
    done = subprocess.run(
        [unshare, "-rm", sys.executable, "-c", _FULL_DISK, str(mount_point)],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "REFUSED store `kept.txt`: the disk is full" in done.stdout, done.stdout
    assert "CONTENT the old content" in done.stdout
    assert "FILES ['kept.txt']" in done.stdout
