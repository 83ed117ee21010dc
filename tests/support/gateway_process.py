"""A real gateway process on a free loopback port, and the fixtures that start one.

``tests/conftest.py`` exposes the fixtures to every test folder.
``gateway_process`` is a factory: call it with the text of a TOML config (or
nothing, for the built-in demo) and get a :class:`GatewayProcess` whose
``.address`` is ``127.0.0.1:PORT``. It runs
``python -m gateway.cli serve [--config FILE] --listen 127.0.0.1:0 --http 127.0.0.1:0``, waits
(at most 20 s) for the ``listening on`` line and a SERVING health check, and
is always stopped when the test ends. The HTTP front end's port is read from its
``HTTP front end and console on URL`` line: ``.http_url`` is ``http://127.0.0.1:PORT/``
(``.http_address`` ``127.0.0.1:PORT``)::

    async def test_something(gateway_process):
        gw = gateway_process('''
            [[services]]
            name = "bot"
            type = "sim-robot"
        ''')
        async with grpc.aio.insecure_channel(gw.address) as channel:
            ...

``demo_gateway`` is one module-wide process serving the demo (see
``gateway/demo.toml``: sim robots, a sensor, devices on TCP and a pty,
``registry``); tests that share it must not leave it changed in ways other
tests would notice.

**A gateway that logged a traceback fails its test.** :meth:`GatewayProcess.stop` (which every
fixture and test calls when it is done with a process) reads everything the process printed and
raises AssertionError when a log entry holds a traceback or says "Task exception was never
retrieved" / "Future exception was never retrieved": nothing a client does may make the gateway log
one. A test that provokes one on purpose declares it first with
:meth:`GatewayProcess.expect_in_log` (a regular expression the entry must match)::

    gw.expect_in_log(r"KeyError: 'crash'")
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

ROOT = Path(__file__).resolve().parents[2]
START_TIMEOUT = 20.0
STOP_TIMEOUT = 5.0
_LISTENING = re.compile(r"^listening on (\S+:\d+)$")
_HTTP = re.compile(r"^HTTP front end and console on (https?://(\S+:\d+)/)$")
#: What no log entry may hold unless a test expects it: a traceback (in a text line, or in a JSON
#: line's ``exception``), and asyncio's words for an exception nobody awaited.
UNEXPECTED_IN_LOG = re.compile(
    r"Traceback \(most recent call last\)"
    r"|Task exception was never retrieved"
    r"|Future exception was never retrieved"
)
#: The first line of a log entry: text (``2026-01-02 03:04:05,678 LEVEL``) or a JSON object. The
#: lines after it that are not themselves a first line (a traceback's) belong to it.
_ENTRY_START = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} |\{)")


def log_entries(output: str) -> list[str]:
    """``output`` cut into log entries, each with the lines that follow it (a traceback's)."""
    entries: list[str] = []
    for line in output.splitlines(keepends=True):
        if _ENTRY_START.match(line) or not entries:
            entries.append(line)
        else:
            entries[-1] += line
    return entries


class GatewayProcess:
    """A running ``psgateway serve`` process."""

    def __init__(
        self,
        args: Sequence[str],
        env: dict[str, str] | None = None,
        *,
        own_group: bool = False,
        cwd: Path = ROOT,
    ) -> None:
        """``own_group``: a process group of its own, like a shell's foreground job (see ``killpg``);
        ``cwd``: the folder it runs in, whose ``gateway`` package ``python -m`` imports first (another
        checkout of the project runs that checkout's gateway)."""
        self.args = list(args)
        self.proc = subprocess.Popen(
            self.args,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            process_group=0 if own_group else None,
        )
        self.address = ""
        #: The HTTP front end's base URL (``http://HOST:PORT/``) and ``HOST:PORT``; "" when it has none.
        self.http_url = ""
        self.http_address = ""
        self._lines: list[str] = []
        #: Patterns of the log entries with a traceback that this process's test provokes on purpose.
        self._expected_in_log: list[re.Pattern[str]] = []
        self._log_checked = False
        self._listening = threading.Event()
        # A thread drains the output so the process never blocks on a full pipe.
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.append(line)
            web = _HTTP.match(line.strip())
            if web and not self.http_url:
                self.http_url, self.http_address = web.group(1), web.group(2)
            m = _LISTENING.match(line.strip())
            if m and not self.address:
                self.address = m.group(1)
                self._listening.set()
        self._listening.set()

    @property
    def output(self) -> str:
        """Everything the process printed so far (log lines go to stderr, merged here)."""
        return "".join(self._lines)

    def expect_in_log(self, pattern: str) -> None:
        """Declare that an entry with a traceback matching ``pattern`` (a regular expression,
        searched) is expected: :meth:`stop` does not fail the test for it."""
        self._expected_in_log.append(re.compile(pattern))

    def unexpected_log_entries(self) -> list[str]:
        """The log entries so far that hold a traceback or an unretrieved exception and that no
        :meth:`expect_in_log` pattern matches."""
        return [
            entry
            for entry in log_entries(self.output)
            if UNEXPECTED_IN_LOG.search(entry)
            and not any(pattern.search(entry) for pattern in self._expected_in_log)
        ]

    def check_log(self) -> None:
        """AssertionError quoting the unexpected entries (see :meth:`unexpected_log_entries`);
        once: a later call (the fixture's, after the test's own) passes."""
        if self._log_checked:
            return
        self._log_checked = True
        unexpected = self.unexpected_log_entries()
        if unexpected:
            shown = "".join(entry[:4000] for entry in unexpected[:5])
            raise AssertionError(
                f"the gateway ({' '.join(self.args[1:4])}) logged {len(unexpected)} unexpected "
                f"traceback(s); declare one a test provokes with expect_in_log(pattern):\n{shown}"
            )

    def wait_ready(
        self, timeout: float = START_TIMEOUT, credentials: grpc.ChannelCredentials | None = None
    ) -> None:
        """Wait for the ``listening on`` line and a SERVING health check; raise with the output if not.

        ``credentials``: how to reach a gateway that serves TLS (plaintext when None).
        """
        if not self._listening.wait(timeout) or not self.address:
            self.stop(check_log=False)
            raise RuntimeError(f"gateway did not start (exit {self.proc.poll()}):\n{self.output}")
        channel = (
            grpc.secure_channel(self.address, credentials)
            if credentials is not None
            else grpc.insecure_channel(self.address)
        )
        with channel:
            stub = health_pb2_grpc.HealthStub(channel)
            reply = stub.Check(
                health_pb2.HealthCheckRequest(service=""), timeout=timeout, wait_for_ready=True
            )
        if reply.status != health_pb2.HealthCheckResponse.SERVING:
            raise RuntimeError(f"gateway is not SERVING: {reply}\n{self.output}")

    def stop(self, timeout: float = STOP_TIMEOUT, check_log: bool = True) -> int:
        """SIGTERM, wait, then SIGKILL (this PID only) if it has not ended; the exit code.

        Then, the first time (unless ``check_log`` is False), :meth:`check_log`: a process that
        logged an unexpected traceback fails the test that stops it."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        self._reader.join(timeout)
        if check_log:
            self.check_log()
        return self.proc.returncode


def start_gateway(
    tmp: Path,
    config: str | None,
    extra_args: Sequence[str] = (),
    credentials: grpc.ChannelCredentials | None = None,
    checkout: Path = ROOT,
) -> GatewayProcess:
    """A ready gateway process serving ``config`` (TOML text written into ``tmp``; None = the demo),
    stopped again if it does not become ready; the caller stops it (the fixtures do). ``checkout``:
    the copy of the project whose gateway runs (another release's worktree: its code alone)."""
    # The HTTP front end on a free port too (a later --http in extra_args wins): never a fixed port.
    args = [sys.executable, "-m", "gateway.cli", "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"]
    if config is not None:
        path = tmp / f"gateway-{len(list(tmp.glob('gateway-*.toml')))}.toml"
        path.write_text(textwrap.dedent(config))
        args += ["--config", str(path)]
    env = {"PYTHONPATH": str(checkout)} if checkout != ROOT else None
    gw = GatewayProcess([*args, *extra_args], env, cwd=checkout)
    try:
        gw.wait_ready(credentials=credentials)
    except BaseException:
        gw.stop(check_log=False)  # never leave a half-started gateway behind; its output is in the error
        raise
    return gw


StartGateway = Callable[..., GatewayProcess]


@pytest.fixture
def gateway_process(tmp_path: Path) -> Iterator[StartGateway]:
    """Factory: ``gateway_process(config_text=None, extra_args=(), credentials=None)`` → a ready
    :class:`GatewayProcess` (``credentials``: grpc channel credentials for a gateway serving TLS)."""
    started: list[GatewayProcess] = []

    def start(
        config: str | None = None,
        extra_args: Sequence[str] = (),
        credentials: grpc.ChannelCredentials | None = None,
    ) -> GatewayProcess:
        gw = start_gateway(tmp_path, config, extra_args, credentials)
        started.append(gw)
        return gw

    yield start
    for gw in started:
        gw.stop(check_log=False)  # every process stopped first, whatever one logged
    for gw in started:
        gw.check_log()


@pytest.fixture(scope="module")
def demo_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    """One gateway process per test module serving the demo config."""
    gw = start_gateway(tmp_path_factory.mktemp("demo"), None)
    yield gw
    gw.stop()  # fails the module's last test when the process logged an unexpected traceback
