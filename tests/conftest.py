"""Fixtures shared by every test folder (see tests/support/gateway_process.py, tests/support/etcd.py,
tests/support/walkthrough.py).

Hypothesis runs without its per-example deadline: these machines are shared, and a slow example
under load says nothing about the property being tested (speed lives in ``bench/``).

The suite runs on two workers side by side (tests/run.sh: pytest-xdist, ``--dist loadgroup``).
Each test file is one group, so its module fixtures (a gateway process, a built firmware) start
once, on one worker; files that build into the same folder on disk share a group
(:data:`SHARED_BUILDS`), so that they never build it at the same time.
"""

from pathlib import Path

import pytest
from hypothesis import settings
from support.etcd import etcd, etcd_server
from support.gateway_process import demo_gateway, gateway_process
from support.walkthrough import fresh_demo_gateway

settings.register_profile("shared-machine", deadline=None)
settings.load_profile("shared-machine")

__all__ = ["demo_gateway", "etcd", "etcd_server", "fresh_demo_gateway", "gateway_process"]

TESTS = Path(__file__).resolve().parent
#: Test files (by name) that build into one shared folder under ``build/``, with that group's name:
#: the compiled example clients (build/cpp, build/go) and the benchmark's Go listeners.
SHARED_BUILDS = {
    "test_cpp_client.py": "compiled clients",
    "test_go_client.py": "compiled clients",
    "test_compiled_clients_agree.py": "compiled clients",
    "test_bench_listener_programs.py": "compiled clients",
}
#: Folders whose tests share one resource outside any one file: the container images and the
#: podman service that tests/containers/setup.sh prepared.
SHARED_FOLDERS = {"containers": "containers"}


@pytest.hookimpl(tryfirst=True)  # before xdist's own, which reads the groups into the test ids
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put each test in its xdist group (see the module docstring)."""
    for item in items:
        path = item.path.resolve().relative_to(TESTS)
        group = SHARED_FOLDERS.get(path.parts[0]) or SHARED_BUILDS.get(path.name) or path.as_posix()
        item.add_marker(pytest.mark.xdist_group(group))
