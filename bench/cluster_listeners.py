"""The programs that open part (t)'s Listen streams: the Go listeners, built on first use, or the Python ones.

Both speak the command line and stdin protocol of :mod:`bench.fanout_listeners`
(``--spread --streams --first --time-limit``; ``ready``, then ``start`` and
``stop`` → one JSON line). They differ in what they cost the machine: a
Python listener process spends more CPU per event than the gateway it
measures (grpc.aio's per-message cost on both sides), so on a machine with
few cores they take the cores the gateways should scale onto. The Go
listeners (``bench/go_listeners/``: HTTP/2 frames read by one goroutine a
connection, every connection read on one 5 ms tick) spend 1–3 µs an
event. They are built offline from Debian's Go sources into
``build/go-listeners`` by ``bench/go_listeners/build.sh`` the first time a
run asks for them (about 5 s; later runs only check that the build is up to
date); without Go, or if the build fails, the Python listeners stand in and
the run says why.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from bench.servers import ROOT

#: The kinds a run may ask for: ``auto`` is ``go`` where it can be built, else ``python``.
KINDS = ("auto", "go", "python")
GO_LISTENERS = ROOT / "bench" / "go_listeners"
GO_BUILD = ROOT / "build" / "go-listeners"
GO_SOURCES = Path("/usr/share/gocode/src")
#: What the Go build needs (a command on PATH, or a path), by the name a note gives it.
GO_NEEDS: dict[str, str | Path] = {
    "go": "go",
    "protoc": "protoc",
    "protoc-gen-go": "protoc-gen-go",
    "golang.org/x/net's HTTP/2 sources": GO_SOURCES / "golang.org/x/net/http2",
    "protobuf-go's sources": GO_SOURCES / "google.golang.org/protobuf",
}
GO_HINT = (
    "tests/run.sh installs them (Debian packages golang-go, golang-golang-x-net-dev, "
    "golang-google-protobuf-dev, protobuf-compiler, protoc-gen-go)"
)
#: A cold build takes about 5 s on two busy cores (protobuf-go compiles once, then comes from the cache).
BUILD_TIMEOUT = 300.0


class ListenerBuildError(RuntimeError):
    """The Go listeners could not be built: the reason, with the build's output."""


@dataclass(frozen=True)
class ListenerProgram:
    """One way to run a listener process: its kind and the command that precedes the options."""

    kind: str
    command: tuple[str, ...]

    def environment(self) -> dict[str, str]:
        """The environment to start it with: the benchmark's own, with the repository on PYTHONPATH."""
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
        return env


PYTHON_LISTENERS = ListenerProgram("python", (sys.executable, "-m", "bench.fanout_listeners"))


def go_missing() -> list[str]:
    """What the Go build needs and this machine lacks (empty when it can be built)."""
    return [
        name
        for name, need in GO_NEEDS.items()
        if not (need.exists() if isinstance(need, Path) else shutil.which(need))
    ]


async def build_go_listeners(build: Path = GO_BUILD) -> ListenerProgram:
    """Build (or bring up to date) the Go listeners into ``build``; ListenerBuildError if it cannot."""
    missing = go_missing()
    if missing:
        raise ListenerBuildError(f"the Go listeners need {', '.join(missing)}: {GO_HINT}")
    process = await asyncio.create_subprocess_exec(
        str(GO_LISTENERS / "build.sh"),
        str(build),
        cwd=ROOT,
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )
    try:
        async with asyncio.timeout(BUILD_TIMEOUT):
            output, _ = await process.communicate()
    except TimeoutError:
        process.kill()
        await process.wait()
        raise ListenerBuildError(
            f"building the Go listeners took longer than {BUILD_TIMEOUT:.0f} s"
        ) from None
    if process.returncode != 0:
        tail = output[-2000:].decode(errors="replace").strip()
        raise ListenerBuildError(f"building the Go listeners failed (exit {process.returncode}):\n{tail}")
    return ListenerProgram("go", (str(build / "bin" / "fanout-listeners"),))


async def listener_programs(kinds: Iterable[str]) -> tuple[list[ListenerProgram], list[str]]:
    """The programs for ``kinds`` (each of :data:`KINDS`), in order, without repeats, and notes on stand-ins.

    ``go`` and ``auto`` build the Go listeners; where they cannot be built the
    Python listeners stand in, and a note says why.
    """
    programs: list[ListenerProgram] = []
    notes: list[str] = []
    go: ListenerProgram | None = None
    go_failure = ""
    for kind in kinds:
        if kind not in KINDS:
            raise ValueError(f"unknown listener kind {kind!r}: choose from {', '.join(KINDS)}")
        program = PYTHON_LISTENERS
        if kind != "python":
            if go is None and not go_failure:
                try:
                    go = await build_go_listeners()
                except ListenerBuildError as error:
                    go_failure = str(error)
                    notes.append(f"the Python listeners stand in for the Go ones: {go_failure}")
            program = go or PYTHON_LISTENERS
        if program not in programs:
            programs.append(program)
    return programs, notes
