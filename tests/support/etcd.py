"""A real etcd server on free loopback ports, in a temporary data folder, for tests of the shared store.

``etcd_server`` is a factory fixture: call it (``tls=`` a :class:`CertificateFiles` for a server that
speaks TLS and asks for client certificates) and get a running :class:`EtcdServer`; every server it
started is stopped when the test ends. A test can stop it (SIGTERM), kill it (SIGKILL), start it
again on the same ports, and wipe its data folder in between (an etcd restarted empty)::

    async def test_something(etcd_server):
        etcd = etcd_server()
        store = EtcdStore(etcd.url, ...)
        ...
        etcd.kill()
        etcd.start(wipe=True)

The ``etcd`` fixture is one plain-text server for the test. Without the ``etcd`` binary on PATH
(Debian's ``etcd-server``; ``tests/run.sh`` installs it) the test skips, saying so.
"""

from __future__ import annotations

import collections
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from support.certs import CertificateFiles
from support.ports import stable_ports

INSTALL_HINT = "bash tests/run.sh installs it (Debian: apt-get install etcd-server)"
#: Seconds etcd may take to say it serves clients: it starts in well under a second when idle; a
#: loaded two-core machine, fsyncing a fresh write-ahead log, has been seen to take a few.
START_TIMEOUT = 20.0
STOP_TIMEOUT = 10.0
#: What etcd logs once its client port answers: 3.4's zap logger says "serving client traffic
#: insecurely" (or "securely"), its other logger and later versions "ready to serve client requests".
_READY = ("serving client traffic", "ready to serve client requests")
#: Starts tried on fresh ports when another process took one first.
_PORT_TRIES = 3
#: Output lines kept for a failure message: the last ones say why etcd did not start.
_KEPT_LINES = 200


def etcd_binary() -> str:
    """The path of the ``etcd`` server; skips the calling test, saying why, when it is absent."""
    path = shutil.which("etcd")
    if path is None:
        pytest.skip(f"the shared store's tests need an etcd server (the `etcd` command): {INSTALL_HINT}")
    return path


class EtcdServer:
    """One etcd process on loopback: a one-member cluster with its own data folder and ports.

    The ports are chosen once, so a server started again answers where the gateways already look.
    """

    def __init__(self, folder: Path, *, tls: CertificateFiles | None = None) -> None:
        self.binary = etcd_binary()
        self.folder = folder
        # etcd syncs its log to disk on every write; on a disk shared with busy neighbours one sync
        # has been seen to take seconds, which delays lease expiry past any test's patience. A
        # RAM-backed folder (Linux's /dev/shm) makes that cost nothing; the test removes it.
        ram = Path("/dev/shm")
        self._ram_folder = Path(tempfile.mkdtemp(prefix="etcd-test-", dir=ram)) if ram.is_dir() else None
        self.data_dir = (self._ram_folder or folder) / "data"
        self.tls = tls
        self.client_port, self.peer_port = stable_ports(2)
        self.proc: subprocess.Popen[str] | None = None
        self._lines: collections.deque[str] = collections.deque(maxlen=_KEPT_LINES)
        #: True once etcd has served on these ports: a later start must use the same ones.
        self.started_once = False

    @property
    def endpoint(self) -> str:
        """``127.0.0.1:PORT`` of the client port."""
        return f"127.0.0.1:{self.client_port}"

    @property
    def url(self) -> str:
        """The ``[registry] store`` value that reaches this server (``etcd://`` or ``etcds://``)."""
        return f"{'etcds' if self.tls else 'etcd'}://{self.endpoint}"

    @property
    def running(self) -> bool:
        """True while the process lives."""
        return self.proc is not None and self.proc.poll() is None

    def output(self) -> str:
        """The last lines etcd wrote (for a failure message)."""
        return "\n".join(self._lines)

    def _command(self) -> list[str]:
        scheme = "https" if self.tls else "http"
        client = f"{scheme}://{self.endpoint}"
        peer = f"http://127.0.0.1:{self.peer_port}"
        command = [
            self.binary,
            "--name=test",
            f"--data-dir={self.data_dir}",
            f"--listen-client-urls={client}",
            f"--advertise-client-urls={client}",
            f"--listen-peer-urls={peer}",
            f"--initial-advertise-peer-urls={peer}",
            f"--initial-cluster=test={peer}",
            "--initial-cluster-state=new",
            "--logger=zap",
            "--log-outputs=stderr",
        ]
        if self.tls:
            command += [
                f"--cert-file={self.tls.server.cert}",
                f"--key-file={self.tls.server.key}",
                f"--trusted-ca-file={self.tls.ca}",
                "--client-cert-auth",
            ]
        return command

    def start(self, *, wipe: bool = False) -> None:
        """Start etcd (again, on the same ports) and wait until it serves clients; ``wipe``: with an
        empty data folder, as a server that lost everything."""
        assert not self.running, "etcd is already running"
        if wipe:
            shutil.rmtree(self.data_dir, ignore_errors=True)
        for _ in range(_PORT_TRIES):
            if self._launch():
                self.started_once = True
                return
            # Another process took a port between stable_ports and etcd's bind: before the first
            # start nobody has been told the ports yet, so take new ones.
            if self.started_once or "address already in use" not in self.output():
                break
            self.client_port, self.peer_port = stable_ports(2)
        raise AssertionError(f"etcd did not start within {START_TIMEOUT} s:\n{self.output()}")

    def _launch(self) -> bool:
        """Run etcd; True once it serves clients, False (and no process) when it does not."""
        self._lines.clear()
        # Each process has its own ready mark: the reader of a killed one may still be reading
        # that one's old "serving" line.
        ready = threading.Event()
        self.proc = subprocess.Popen(
            self._command(),
            cwd=self.folder,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        # A thread drains the output so etcd never blocks on a full pipe.
        threading.Thread(target=self._read, args=(self.proc, ready), daemon=True).start()
        deadline = time.monotonic() + START_TIMEOUT
        while not ready.wait(0.05):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.kill()
                return False
        return True

    def _read(self, proc: subprocess.Popen[str], ready: threading.Event) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if proc is self.proc:
                self._lines.append(line.rstrip("\n"))
            if any(mark in line for mark in _READY):
                ready.set()

    def stop(self) -> None:
        """Stop etcd politely (SIGTERM), as an operator would; SIGKILL if it lingers."""
        self._end(signal.SIGTERM)

    def kill(self) -> None:
        """SIGKILL etcd, as a crash would."""
        self._end(signal.SIGKILL)

    def remove(self) -> None:
        """Kill etcd and delete its data folder."""
        self.kill()
        shutil.rmtree(self.data_dir, ignore_errors=True)
        if self._ram_folder is not None:
            shutil.rmtree(self._ram_folder, ignore_errors=True)

    def _end(self, how: signal.Signals) -> None:
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(how)
        try:
            proc.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(STOP_TIMEOUT)


@pytest.fixture
def etcd_server(tmp_path: Path) -> Iterator[Callable[..., EtcdServer]]:
    """A factory of running etcd servers (``tls=`` certificates for TLS); all stopped at the end."""
    servers: list[EtcdServer] = []

    def start(*, tls: CertificateFiles | None = None) -> EtcdServer:
        server = EtcdServer(tmp_path / f"etcd{len(servers)}", tls=tls)
        server.folder.mkdir(parents=True)
        servers.append(server)
        server.start()
        return server

    yield start
    for server in servers:
        server.remove()


@pytest.fixture
def etcd(etcd_server: Callable[..., EtcdServer]) -> EtcdServer:
    """One running plain-text etcd server for the test."""
    return etcd_server()
