"""The gateway's image, run by podman and driven through testcontainers-python and grpcurl.

``tests/containers/setup.sh`` (run by ``tests/run.sh``) builds the image and writes
``build/containers/status``: ``ready: IMAGE`` or ``skip: WHY``. These fixtures start podman's
Docker-compatible API (``podman system service``) on a socket of their own and point
testcontainers at it: no Ryuk (podman has no reaper image here, and the fixtures remove what they
start), the docker host's own address for mapped ports, and 127.0.0.1 as that host.

Every container and network the tests create carries ``RUN_LABEL`` = this test process's PID. When
the session ends, what carries its PID is removed; when one starts, what carries the PID of a test
process that is gone (a run that was killed) is removed too. A container left running would keep
its published port forwarded: every later connection to 127.0.0.1 on that port, whoever listens
there, would be sent to the dead container.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.podman_runs import remove_labelled

ROOT = Path(__file__).resolve().parents[2]
STATUS = ROOT / "build" / "containers" / "status"
CONTAINERS_CONF = ROOT / "build" / "containers" / "containers.conf"
#: Seconds podman's API service may take to open its socket.
SERVICE_START = 20.0


def _image_or_skip() -> str:
    if shutil.which("podman") is None:
        pytest.skip("no container runtime: podman is not installed (tests/run.sh installs Debian's podman)")
    if not STATUS.exists():
        pytest.skip(f"the image is not built: run tests/containers/setup.sh ({STATUS} is missing)")
    kind, _, detail = STATUS.read_text().strip().partition(": ")
    if kind != "ready":
        pytest.skip(f"container tests skipped by tests/containers/setup.sh: {detail}")
    return detail


@pytest.fixture(scope="session")
def image() -> str:
    """The tag of the image that setup.sh built from this tree."""
    return _image_or_skip()


ETCD_STATUS = ROOT / "build" / "containers" / "etcd-status"


@pytest.fixture(scope="session")
def etcd_image(image: str) -> str:
    """The etcd image of the compose cluster: the one setup.sh built from the host's etcd, or ETCD_IMAGE."""
    if not ETCD_STATUS.exists():
        pytest.skip(f"no etcd image: run tests/containers/setup.sh ({ETCD_STATUS} is missing)")
    kind, _, detail = ETCD_STATUS.read_text().strip().partition(": ")
    if kind != "ready":
        pytest.skip(f"the compose cluster's test skipped by tests/containers/setup.sh: {detail}")
    return detail


@pytest.fixture(scope="session")
def podman_env(image: str) -> dict[str, str]:
    """The environment podman commands run with (its containers.conf from setup.sh)."""
    return {**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)}


@pytest.fixture(scope="session")
def docker_api(podman_env: dict[str, str], tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A Docker-compatible API socket served by ``podman system service``; testcontainers uses it."""
    left = remove_labelled(podman_env, run=None)
    if left:
        print(f"removed what killed test runs left behind: {', '.join(left)}")
    sock = tmp_path_factory.mktemp("podman") / "podman.sock"
    url = f"unix://{sock}"
    service = subprocess.Popen(
        ["podman", "system", "service", "--time=0", url],
        env=podman_env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + SERVICE_START
        while not sock.exists():
            if service.poll() is not None:
                err = service.stderr.read().decode() if service.stderr else ""
                pytest.fail(f"podman system service ended at once: {err.strip()}")
            if time.monotonic() > deadline:
                pytest.fail(f"podman system service opened no socket within {SERVICE_START} s")
            time.sleep(0.05)
        # testcontainers reads these when it is first imported: set them before any import of it.
        os.environ["DOCKER_HOST"] = url
        os.environ["TESTCONTAINERS_RYUK_DISABLED"] = "true"
        os.environ["TESTCONTAINERS_CONNECTION_MODE"] = "docker_host"
        os.environ["TESTCONTAINERS_HOST_OVERRIDE"] = "127.0.0.1"
        yield url
    finally:
        remove_labelled(podman_env, run=str(os.getpid()))
        service.terminate()
        try:
            service.wait(timeout=10)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait(timeout=10)
