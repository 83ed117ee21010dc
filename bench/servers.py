"""Server processes under test: start one, find its port, watch its CPU and memory, end it by PID."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import os
import re
import signal
import sys
from pathlib import Path

import grpc

ROOT = Path(__file__).resolve().parent.parent
_LISTENING = re.compile(r"listening on (\S+):(\d+)")

#: How long a server may take to print its address.
START_TIMEOUT = 30.0
STOP_TIMEOUT = 5.0


class ServerError(RuntimeError):
    """A server under test did not start, or died."""


class ServerProcess:
    """One server under test, running as a child process on 127.0.0.1."""

    def __init__(self, kind: str, process: asyncio.subprocess.Process, address: str) -> None:
        self.kind = kind
        self.process = process
        self.address = address
        self.pid = process.pid
        # Imported here, not at the top: `python -m bench --help` needs only the runtime packages.
        import psutil  # type: ignore[import-untyped,unused-ignore]

        self._ps = psutil.Process(process.pid)
        self._log: collections.deque[str] = collections.deque(maxlen=40)
        self._drain: asyncio.Task[None] | None = None

    @classmethod
    async def start(cls, kind: str, argv: list[str], *, address_on: str = "stderr") -> ServerProcess:
        """Run ``python -m <argv>`` and wait for its ``listening on HOST:PORT`` line.

        The line is looked for on stderr, or with ``address_on="stdout"`` on
        stdout (stderr then goes to the same pipe), for programs that print
        their address there (``python -m services.device``).
        """
        on_stdout = address_on == "stdout"
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            *argv,
            cwd=ROOT,
            env=env,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE if on_stdout else asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.STDOUT if on_stdout else asyncio.subprocess.PIPE,
        )
        output = process.stdout if on_stdout else process.stderr
        assert output is not None
        seen: list[str] = []
        try:
            async with asyncio.timeout(START_TIMEOUT):
                while True:
                    raw = await output.readline()
                    if not raw:
                        raise ServerError(f"{kind} server exited before listening:\n" + "".join(seen[-20:]))
                    line = raw.decode(errors="replace")
                    seen.append(line)
                    match = _LISTENING.search(line)
                    if match:
                        break
        except TimeoutError:
            await _end(process)
            raise ServerError(f"{kind} server did not print its address in {START_TIMEOUT:.0f} s") from None
        except BaseException:
            await _end(process)
            raise
        server = cls(kind, process, f"{match.group(1)}:{match.group(2)}")
        server._log.extend(seen)
        server._drain = asyncio.create_task(server._drain_output(output))
        return server

    async def _drain_output(self, output: asyncio.StreamReader) -> None:
        # Keep reading so that a chatty server never blocks on a full pipe.
        while raw := await output.readline():
            self._log.append(raw.decode(errors="replace"))

    @property
    def log_tail(self) -> str:
        """The last lines the server wrote to stderr."""
        return "".join(self._log)

    def check_alive(self) -> None:
        """Raise :class:`ServerError` if the server has exited."""
        if self.process.returncode is not None:
            raise ServerError(f"{self.kind} server exited with {self.process.returncode}:\n{self.log_tail}")

    def cpu_seconds(self) -> float:
        """User plus system CPU time the server has used so far (all its threads)."""
        times = self._ps.cpu_times()
        return float(times.user + times.system)

    def rss_bytes(self) -> int:
        """Resident set size of the server process."""
        return int(self._ps.memory_info().rss)

    def open_files(self) -> int:
        """File descriptors the server process holds (sockets included)."""
        return int(self._ps.num_fds())

    def connections_to(self, ports: set[int]) -> int:
        """Established TCP connections the server process holds to a remote port among ``ports``."""
        return sum(
            1
            for connection in self._ps.net_connections(kind="tcp")
            if connection.status == "ESTABLISHED" and connection.raddr and connection.raddr.port in ports
        )

    async def stop(self) -> None:
        """End the server (SIGTERM, then SIGKILL after a grace period), by its PID."""
        await _end(self.process)
        if self._drain is not None:
            self._drain.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._drain


async def _end(process: asyncio.subprocess.Process) -> None:
    if process.stdin is not None:
        process.stdin.close()
    if process.returncode is None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(process.pid, signal.SIGTERM)
        try:
            async with asyncio.timeout(STOP_TIMEOUT):
                await process.wait()
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGKILL)
            await process.wait()


#: Metadata sent with every call of a measurement (a bearer token), as grpc takes it.
Metadata = tuple[tuple[str, str], ...]


def open_channel(address: str, credentials: grpc.ChannelCredentials | None = None) -> grpc.aio.Channel:
    """A channel to a server under test: TLS with ``credentials``, plaintext without."""
    if credentials is None:
        return grpc.aio.insecure_channel(address)
    return grpc.aio.secure_channel(address, credentials)


async def end_process(process: asyncio.subprocess.Process) -> None:
    """End a child process of the benchmark by its PID: stdin closed, SIGTERM, then SIGKILL after a while."""
    await _end(process)
