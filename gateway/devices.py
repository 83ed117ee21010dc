"""Devices the gateway starts itself: Python stand-ins for microcontrollers, one process each.

A ``[[devices]]`` entry of the configuration (:class:`gateway.config.DeviceEntry`)
becomes a child process running the device server (``services.device``)::

    python -m services.device --service sim-robot --name rover1 --exit-with-parent --tcp 127.0.0.1:0
    python -m services.device --service sim-robot --name rover2 --exit-with-parent --pty

The child serves the service over the line protocol on raw TCP or on a
pseudo-terminal, and prints one line saying where:
``listening on HOST:PORT`` or ``serial port /dev/pts/N``. The gateway reads that
line (bounded wait), then reaches the device through its ``tcp://`` or
``serial://`` proxy like any other device, and ends the child by its PID at
shutdown (SIGTERM, a bounded wait, then SIGKILL).

A child that ends while the gateway runs is started again (:class:`SupervisedDevice`):
after 0.5 s, doubling up to 30 s while it keeps failing, back to 0.5 s once a process
has run for a minute; each exit and restart is logged. The proxy's address does not
change: a TCP device is started again on the port it had, and a serial one is reached
through a link in a private folder that is pointed at each new pseudo-terminal. The
proxy reconnects by itself, as it does to any device that went away.

On a pseudo-terminal the child plays the microcontroller's end of the cable:
it serves the master side and reports the slave's path, which the gateway's
serial proxy opens with pyserial (:meth:`services.device.DeviceServer.serve_pty`).
The child's stdin is a pipe from the gateway: it ends when that pipe closes,
even if the gateway is killed. It runs in a process group of its own, so a
Ctrl-C in the gateway's terminal reaches only the gateway, which closes the
proxies first and then ends the children.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import os
import re
import shutil
import signal
import sys
import tempfile
from collections.abc import Callable
from urllib.parse import urlsplit

from gateway.config import DeviceEntry
from gateway.logs import outside_requests
from services.kernel.errors import Unavailable

log = logging.getLogger(__name__)

#: Seconds a device process may take to say where it serves, unless ``[gateway] device_start_timeout``
#: says otherwise (a loaded machine can take longer than this to start a Python process).
START_TIMEOUT = 30.0
#: Seconds a device process gets to end after SIGTERM before SIGKILL.
STOP_TIMEOUT = 3.0

#: Seconds before the first restart of a device process that ended, doubled after each
#: restart that did not last, up to RESTART_MAX_S; reset once a process ran RESTART_STEADY_S.
RESTART_INITIAL_S = 0.5
RESTART_MAX_S = 30.0
RESTART_STEADY_S = 60.0

_TCP_LINE = re.compile(r"listening on (\S+):(\d+)")
_PTY_LINE = re.compile(r"serial port (/\S+)")


class DeviceProcess:
    """A running device child process and the URL the gateway reaches it at."""

    def __init__(self, name: str, url: str, process: asyncio.subprocess.Process) -> None:
        self.name = name
        self.url = url
        self.process = process
        self._drain: asyncio.Task[None] | None = None
        if process.stdout is not None:
            self._drain = asyncio.create_task(_drain(name, process.stdout), context=outside_requests(name))

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self.process.pid

    async def aclose(self, wait_s: float = STOP_TIMEOUT) -> None:
        """End the child: SIGTERM, wait up to ``wait_s`` seconds, then SIGKILL. Idempotent."""
        await _terminate(self.process, wait_s)
        if self._drain is not None:
            self._drain.cancel()
            await asyncio.gather(self._drain, return_exceptions=True)
        log.info(
            "device %s stopped (pid %d, exit %s)",
            self.name,
            self.pid,
            self.process.returncode,
            extra={"service": self.name},
        )


async def _drain(name: str, stream: asyncio.StreamReader) -> None:
    # The child prints nothing more after its address; anything else is shown, never left to fill the pipe.
    while line := await stream.readline():
        log.info("device %s: %s", name, line.decode(errors="replace").rstrip())


async def _terminate(process: asyncio.subprocess.Process, wait_s: float) -> None:
    if process.returncode is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        process.send_signal(signal.SIGTERM)
    try:
        await asyncio.wait_for(process.wait(), wait_s)
    except TimeoutError:
        with contextlib.suppress(ProcessLookupError):
            process.kill()
        await asyncio.wait_for(process.wait(), wait_s)
    if process.stdin is not None:
        process.stdin.close()


def device_command(entry: DeviceEntry) -> list[str]:
    """The command line of the child process for ``entry``."""
    args = [sys.executable, "-m", "services.device", "--service", entry.type, "--name", entry.name]
    for key, value in entry.options.items():
        args += ["--option", f"{key}={json.dumps(value)}"]
    args.append("--exit-with-parent")
    if "maxline" in entry.proxy:
        # The proxy takes lines this long from the device (large binary values, docs/line-protocol.md
        # §11); the device then takes and sends them too.
        args += ["--max-line", str(entry.proxy["maxline"])]
    if entry.tcp:
        return [*args, "--tcp", entry.tcp]
    return [*args, "--pty"]


async def start_device(entry: DeviceEntry, *, wait_s: float = START_TIMEOUT) -> DeviceProcess:
    """Start the device process for ``entry`` and wait (at most ``wait_s`` s) until it says where it serves.

    Raises InvalidArgument for bad options and Unavailable when the process
    ends or stays silent; the process is ended in both cases.
    """
    from services.apps.catalog import build

    build(entry.type, entry.options)  # bad options fail here, with the catalog's message
    process = await asyncio.create_subprocess_exec(
        *device_command(entry),
        stdin=asyncio.subprocess.PIPE,  # the child ends when this pipe closes, even if the gateway is killed
        stdout=asyncio.subprocess.PIPE,
        # A process group of its own: Ctrl-C in a terminal signals the whole foreground group, and a
        # device that died at once would be reported as lost by its proxy while the gateway shuts
        # down. The gateway ends its devices itself, after closing their proxies.
        process_group=0,
    )
    try:
        async with asyncio.timeout(wait_s):
            first = (await process.stdout.readline()).decode(errors="replace").strip()  # type: ignore[union-attr]
    except TimeoutError:
        await _terminate(process, STOP_TIMEOUT)
        raise Unavailable(
            f"device {entry.name}: did not say where it serves within {wait_s:g} s"
            " (raise [gateway] device_start_timeout on a loaded machine)"
        ) from None
    except BaseException:
        await _terminate(process, STOP_TIMEOUT)
        raise
    if m := _TCP_LINE.fullmatch(first):
        url = f"tcp://{m.group(1)}:{m.group(2)}"
    elif m := _PTY_LINE.fullmatch(first):
        url = f"serial://{m.group(1)}?baudrate={entry.baudrate}"
    else:
        await _terminate(process, STOP_TIMEOUT)
        raise Unavailable(
            f"device {entry.name}: the device process did not start (exit {process.returncode},"
            f" said {first!r}; its errors are in the log above)"
        )
    device = DeviceProcess(entry.name, url, process)
    log.info("device %s started (pid %d) at %s", entry.name, device.pid, url, extra={"service": entry.name})
    return device


class SupervisedDevice:
    """A device process kept running: started again with capped backoff whenever it ends.

    :attr:`url` stays the same across restarts (see the module's docstring), so the proxy
    built on it reconnects by itself. :meth:`aclose` stops the supervision and the process.
    """

    def __init__(
        self,
        entry: DeviceEntry,
        device: DeviceProcess,
        *,
        initial_s: float = RESTART_INITIAL_S,
        max_s: float = RESTART_MAX_S,
        steady_s: float = RESTART_STEADY_S,
        start_wait_s: float = START_TIMEOUT,
    ) -> None:
        self.name = entry.name
        self.start_wait_s = start_wait_s
        self.device = device
        self.initial_s = initial_s
        self.max_s = max_s
        self.steady_s = steady_s
        #: Restarts so far.
        self.restarts = 0
        #: Called with the device's own URL after each restart (the gateway reserves a new serial line).
        self.on_restart: Callable[[str], None] | None = None
        self._closing = False
        self._link_dir = ""
        parts = urlsplit(device.url)
        if parts.scheme == "tcp":
            # Started again on the port it had, so the proxy's URL still reaches it.
            self._again = dataclasses.replace(entry, tcp=parts.netloc)
            self.url = device.url
        else:
            self._again = entry
            self._link_dir = tempfile.mkdtemp(prefix="psgateway-device-")
            self._link = os.path.join(self._link_dir, "tty")
            self._relink()
            self.url = f"serial://{self._link}?{parts.query}"
        self._task = asyncio.create_task(
            self._watch(), name=f"device {self.name} supervisor", context=outside_requests(self.name)
        )

    @property
    def pid(self) -> int:
        """The process id of the current device process."""
        return self.device.pid

    def _relink(self) -> None:
        if not self._link_dir:
            return
        target = urlsplit(self.device.url).path
        temporary = f"{self._link}.new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        os.symlink(target, temporary)
        os.replace(temporary, self._link)  # atomic: the proxy never finds the link missing

    async def _watch(self) -> None:
        loop = asyncio.get_running_loop()
        delay = self.initial_s
        while True:
            began = loop.time()
            await self.device.process.wait()
            if self._closing:
                return
            ran = loop.time() - began
            if ran >= self.steady_s:
                delay = self.initial_s
            log.warning(
                "device %s: its process %d ended (exit %s) after %.1f s; starting it again in %g s",
                self.name,
                self.device.pid,
                self.device.process.returncode,
                ran,
                delay,
            )
            await self.device.aclose()
            while True:
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.max_s)
                try:
                    device = await start_device(self._again, wait_s=self.start_wait_s)
                except Exception as exc:  # any failure is logged and tried again
                    log.warning(
                        "device %s: could not start it again (%s); next try in %g s", self.name, exc, delay
                    )
                    continue
                self.device = device
                self.restarts += 1
                self._relink()
                if self.on_restart is not None:
                    self.on_restart(device.url)
                log.info(
                    "device %s: started again (pid %d, restart %d)", self.name, device.pid, self.restarts
                )
                break

    async def aclose(self) -> None:
        """Stop supervising and end the process (SIGTERM, then SIGKILL). Idempotent."""
        self._closing = True
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)
        await self.device.aclose()
        if self._link_dir:
            shutil.rmtree(self._link_dir, ignore_errors=True)


async def start_supervised(entry: DeviceEntry, *, wait_s: float = START_TIMEOUT) -> SupervisedDevice:
    """:func:`start_device`, then kept running by a :class:`SupervisedDevice` (restarts wait as long)."""
    return SupervisedDevice(entry, await start_device(entry, wait_s=wait_s), start_wait_s=wait_s)


__all__ = [
    "START_TIMEOUT",
    "STOP_TIMEOUT",
    "DeviceProcess",
    "SupervisedDevice",
    "device_command",
    "start_device",
    "start_supervised",
]
