"""The one-command cluster: etcd and three gateways on loopback ports, devices spread across them.

::

    python -m gateway.cluster                          # etcd, 3 gateways, 6 devices; Ctrl-C stops all
    python -m gateway.cluster --gateways 4 --devices 8
    python -m gateway.cluster --base-port 0            # free ports (etcd's too), printed
    python -m gateway.cluster --once --picture docs/images/scale-out-owners.svg

It starts Debian's ``etcd`` (a one-member cluster in a temporary folder), then the gateways
(``python -m gateway serve``, each with ``[registry] store`` naming that etcd, a line listener and
the HTTP front end), then simulated line devices (``python -m services.device``): most on a
TCP port of their own, registered by a Set on one gateway each in turn, the others dialling in to a
gateway's line listener. Once every gateway lists every device it prints who owns what, and runs
until Ctrl-C (or SIGTERM), when it stops every process it started, by PID: the devices, the
gateways, then etcd. Every process writes its log in the temporary folder (``--keep`` keeps it).

Meanwhile it watches what it started: a process that ends (killed to watch a failover, or
crashed) is named with its exit status and the end of its log; when it was a gateway, who owns
what is printed again once the lease has run out and the others have taken its devices over.
When no gateway is left, it stops everything and exits with status 1.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import grpc

from gateway.cluster.picture import draw_owners
from gateway.cluster.records import GatewayRecord, Ownership, Registration
from gateway.ports import PortInUse, check_port_free
from gateway.stores.etcd import MAX_LEASE, MIN_LEASE
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.device.cli import bounded_int
from services.kernel.values import parse_names

__all__ = ["DESCRIPTION", "main"]

DESCRIPTION = (
    "Start etcd and a cluster of gateways on loopback ports, with simulated devices spread across them."
)
ETCD_MISSING = (
    "etcd is not installed: the cluster keeps its registry in etcd. On Debian or Ubuntu: "
    "sudo apt-get install etcd-server (the `etcd` command must be on PATH)"
)
#: Seconds a process may take to say it is ready (a loaded two-core machine included).
START_TIMEOUT = 30.0
#: Seconds a process gets to end after SIGTERM before it is killed.
STOP_TIMEOUT = 5.0
#: Most gateways and devices one command starts: a demonstration, not a deployment.
MAX_GATEWAYS = 9
MAX_DEVICES = 64
#: etcd's own client port (its peer port is the next, as etcd's 2380).
DEFAULT_ETCD_PORT = 2379


@dataclass
class Child:
    """A process this command started: its PID, what it is, and its log file."""

    what: str
    proc: subprocess.Popen[bytes]
    log: Path
    _log_file: IO[bytes] = field(repr=False)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""

    async def wait_for(self, pattern: str, within: float = START_TIMEOUT) -> re.Match[str]:
        """Wait until the log has a line matching ``pattern``; RuntimeError, with the log's end, if not."""
        regex = re.compile(pattern, re.MULTILINE)
        deadline = time.monotonic() + within
        while True:
            found = regex.search(self.output())
            if found is not None:
                return found
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = "\n".join(self.output().splitlines()[-15:])
                status = (
                    f"exited with {self.proc.returncode}" if self.proc.poll() is not None else "timed out"
                )
                raise RuntimeError(f"{self.what} did not start ({status}); its log ends:\n{tail}")
            await asyncio.sleep(0.05)

    def stop(self) -> None:
        """SIGTERM, wait, then SIGKILL: this PID only."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(STOP_TIMEOUT)
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self._log_file.close()


@dataclass(frozen=True)
class GatewayPorts:
    """Where one gateway of the cluster listens."""

    id: str
    grpc: int
    line: int
    http: int

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.grpc}"

    @property
    def line_address(self) -> str:
        return f"127.0.0.1:{self.line}"


#: Where Linux hands out the local ports of outgoing connections; free ports are picked below it,
#: where no gateway's own connection (to etcd, to another gateway) can take one before its server.
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_LOWEST_PORT = 10000


class _FreePorts:
    """Free loopback ports below the ephemeral range, all held open until the last is picked (the
    kernel never hands out one twice, and no outgoing connection takes one meanwhile)."""

    def __init__(self) -> None:
        self._held = contextlib.ExitStack()
        try:
            high = int(_EPHEMERAL_RANGE.read_text().split()[0])
        except (OSError, ValueError, IndexError):
            high = 32768
        self._candidates = random.sample(range(_LOWEST_PORT, max(high, _LOWEST_PORT + 1000)), 2000)

    def take(self) -> int:
        while self._candidates:
            port = self._candidates.pop()
            sock = self._held.enter_context(socket.socket())
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
        raise RuntimeError("no free loopback port below the ephemeral range")

    def release(self) -> None:
        self._held.close()


class Cluster:
    """The processes of one cluster, started in order and stopped in reverse (see the module docstring)."""

    def __init__(self, folder: Path, args: argparse.Namespace) -> None:
        self.folder = folder
        self.args = args
        self.children: list[Child] = []
        free = _FreePorts()
        fixed = args.base_port != 0
        # --base-port 0 means every port a free one, etcd's too, unless --etcd-port names one.
        etcd_port = args.etcd_port if args.etcd_port is not None else (DEFAULT_ETCD_PORT if fixed else 0)

        def port(base: int, offset: int, *, chosen: bool) -> int:
            return base + offset if chosen else free.take()

        try:
            self.etcd_port = port(etcd_port, 0, chosen=etcd_port != 0)
            self.etcd_peer_port = port(etcd_port, 1, chosen=etcd_port != 0)
            self.gateways = [
                GatewayPorts(
                    f"gw{i + 1}",
                    port(args.base_port, i, chosen=fixed),
                    port(args.line_port, i, chosen=fixed),
                    port(args.http_port, i, chosen=fixed),
                )
                for i in range(args.gateways)
            ]
        finally:
            free.release()
        #: Device name → how it is reached ("tcp://..." or "dials in to gwN").
        self.devices: dict[str, str] = {}

    @property
    def store_url(self) -> str:
        return f"etcd://127.0.0.1:{self.etcd_port}"

    def _spawn(self, what: str, command: list[str], *, stdin: bool = False) -> Child:
        log = self.folder / f"{what.replace(' ', '-')}.log"
        log_file = log.open("wb")
        proc = subprocess.Popen(
            command,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # Ctrl-C reaches this command only, which stops the others in order
        )
        child = Child(what, proc, log, log_file)
        self.children.append(child)
        return child

    async def start_etcd(self, binary: str) -> None:
        client = f"http://127.0.0.1:{self.etcd_port}"
        peer = f"http://127.0.0.1:{self.etcd_peer_port}"
        for port, what in ((self.etcd_port, "etcd's client port"), (self.etcd_peer_port, "etcd's peer port")):
            try:
                check_port_free(f"127.0.0.1:{port}", what)
            except PortInUse as exc:  # etcd would only say so in a JSON log line
                raise RuntimeError(f"{exc}; --etcd-port 0 picks free ones") from None
        etcd = self._spawn(
            "etcd",
            [
                binary,
                "--name=cluster",
                f"--data-dir={self.folder / 'etcd-data'}",
                f"--listen-client-urls={client}",
                f"--advertise-client-urls={client}",
                f"--listen-peer-urls={peer}",
                f"--initial-advertise-peer-urls={peer}",
                f"--initial-cluster=cluster={peer}",
                "--logger=zap",
                "--log-outputs=stderr",
            ],
        )
        await etcd.wait_for(r"serving client traffic|ready to serve client requests")

    def _config(self, ports: GatewayPorts) -> Path:
        path = self.folder / f"{ports.id}.toml"
        path.write_text(
            f"""# {ports.id} of the cluster started by python -m gateway.cluster
[gateway]
listen = "{ports.address}"
line_listen = "{ports.line_address}"

[http]
listen = "127.0.0.1:{ports.http}"

[registry]
store = "{self.store_url}"
store_lease = {self.args.lease:g}
gateway_id = "{ports.id}"
period = 1.0
"""
        )
        return path

    async def start_gateways(self) -> None:
        started = [
            (
                ports,
                self._spawn(
                    ports.id, [sys.executable, "-m", "gateway", "serve", "--config", str(self._config(ports))]
                ),
            )
            for ports in self.gateways
        ]
        for ports, child in started:
            await child.wait_for(rf"^listening on {re.escape(ports.address)}$")

    async def start_devices(self) -> None:
        """Devices spread over the gateways in turn: the first round registered by a Set on each
        gateway, the next round dialling in to each gateway's line listener, and so on."""
        kinds = ("sim-sensor", "sim-robot")
        registering: list[tuple[str, str, GatewayPorts]] = []
        for i in range(self.args.devices):
            kind = kinds[i % len(kinds)]
            name = f"{'thermo' if kind == 'sim-sensor' else 'rover'}{i + 1}"
            gateway = self.gateways[i % len(self.gateways)]
            dials_in = (i // len(self.gateways)) % 2 == 1
            command = [sys.executable, "-m", "services.device", "--service", kind, "--name", name]
            if dials_in:
                command += ["--connect", gateway.line_address, "--exit-with-parent"]
                self._spawn(f"device {name}", command, stdin=True)
                self.devices[name] = f"dials in to {gateway.id}"
                continue
            child = self._spawn(
                f"device {name}", [*command, "--tcp", "127.0.0.1:0", "--exit-with-parent"], stdin=True
            )
            found = await child.wait_for(r"^listening on (\S+:\d+)$")
            url = f"tcp://{found.group(1)}"
            self.devices[name] = url
            registering.append((name, url, gateway))
        for name, url, gateway in registering:
            await _register(gateway.address, name, url)

    async def wait_listed(self) -> None:
        """Wait until every gateway's registry lists every device."""
        deadline = time.monotonic() + START_TIMEOUT
        for gateway in self.gateways:
            while True:
                names = await _registered(gateway.address)
                if set(self.devices) <= names:
                    break
                if time.monotonic() > deadline:
                    missing = ", ".join(sorted(set(self.devices) - names))
                    raise RuntimeError(f"{gateway.id} does not list {missing} after {START_TIMEOUT:g} s")
                await asyncio.sleep(0.1)

    def live_gateways(self) -> list[GatewayPorts]:
        """The gateways whose process still runs."""
        running = {child.what for child in self.children if child.proc.poll() is None}
        return [g for g in self.gateways if g.id in running]

    async def ownership(self) -> Ownership:
        """The gateways, who owns each device and where each is registered, as the first live gateway
        says (RuntimeError when none is left)."""
        live = self.live_gateways()
        if not live:
            raise RuntimeError("no gateway of the cluster is running")
        address = live[0].address
        gateways = {g.id: GatewayRecord(g.address, f"127.0.0.1:{g.http}", g.line_address) for g in live}
        owners: dict[str, str] = {}
        registrations: dict[str, Registration] = {}
        for name in self.devices:
            registrations[name] = Registration(await _get(address, "registry", f"services.{name}.url"))
            owner = await _get(address, "registry", f"services.{name}.owner")
            if owner:
                owners[name] = owner
        return Ownership(self.store_url, gateways, owners, registrations)

    def stop(self) -> None:
        """Stop every process, devices first, etcd last, each by its PID."""
        for child in reversed(self.children):
            child.stop()


async def _register(address: str, name: str, url: str) -> None:
    async with grpc.aio.insecure_channel(address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Set(
            pb.SetRequest(service="registry", property=f"services.{name}", value=url), timeout=15.0
        )


async def _get(address: str, service: str, path: str, parameters: dict[str, str] | None = None) -> str:
    async with grpc.aio.insecure_channel(address) as channel:
        reply = await pb_grpc.PropertyServiceStub(channel).Get(
            pb.GetRequest(service=service, property=path, parameters=parameters), timeout=10.0
        )
        return str(reply.value)


async def _registered(address: str) -> set[str]:
    """Every name the registry of the gateway at ``address`` lists, read a page at a time (its
    ``service_names``): ``services`` is one value, which passes 64 KiB at about 6,000 names."""
    names: set[str] = set()
    after = ""
    while page := parse_names(await _get(address, "registry", "service_names", {"after": after})):
        names.update(page)
        after = page[-1]
    return names


def print_owners(ownership: Ownership, folder: Path) -> None:
    """Who owns what, as two tables on stdout."""
    print(f"etcd: {ownership.store}   (logs in {folder})")
    print(f"{'gateway':8} {'gRPC':17} {'HTTP and console':26} {'line':17} owns")
    for gateway, record in sorted(ownership.gateways.items()):
        owned = ", ".join(ownership.owned_by(gateway)) or "-"
        print(f"{gateway:8} {record.address:17} {'http://' + record.http + '/':26} {record.line:17} {owned}")
    print(f"{'device':10} {'registered as':30} owner")
    for name, registration in sorted(ownership.registrations.items()):
        print(f"{name:10} {registration.url:30} {ownership.owners.get(name, '(none yet)')}")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m gateway.cluster",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="""examples:
  python -m gateway.cluster                     etcd on 2379, gateways on 50061-50063 (HTTP 8081-8083,
                                                line 7101-7103), 6 devices; Ctrl-C stops everything
  python -m gateway.cluster --base-port 0       every port a free one, etcd's too (printed)
  python -m gateway.cluster --once --picture docs/images/scale-out-owners.svg
                                                draw who owns what, then stop

then, from another shell (any gateway answers for any device):
  psctl --target 127.0.0.1:50062 get thermo1 data
  psctl --target 127.0.0.1:50063 get registry services.thermo1.owner
  grpcurl -plaintext -d '{"service":"thermo1","property":"data"}' \\
      127.0.0.1:50061 propertyservice.v1.PropertyService/Listen
""",
    )
    # Whole numbers within bounds: (option, lowest, highest, default, what it is).
    numbers = (
        ("--gateways", 1, MAX_GATEWAYS, 3, "gateways to start"),
        ("--devices", 0, MAX_DEVICES, 6, "simulated devices to start"),
        ("--base-port", 0, 65000, 50061, "gRPC port of the first gateway, the others follow; 0: all free"),
        ("--line-port", 1, 65000, 7101, "line listener of the first gateway"),
        ("--http-port", 1, 65000, 8081, "HTTP port of the first gateway"),
    )
    for option, low, high, default, what in numbers:
        kind = bounded_int(option.removeprefix("--"), low, high)
        parser.add_argument(option, type=kind, default=default, help=f"{what} (default {default})")
    parser.add_argument(
        "--etcd-port",
        type=bounded_int("etcd-port", 0, 65000),
        help=f"etcd's client port, its peer port the next; 0: free ones "
        f"(default {DEFAULT_ETCD_PORT}, with --base-port 0 free ones)",
    )
    parser.add_argument(
        "--lease",
        type=_lease,
        default=3.0,
        help="seconds of each gateway's lease: how soon a dead one's devices move (default 3)",
    )
    parser.add_argument(
        "--picture", type=Path, help="write an SVG of who owns what to this file once the cluster is up"
    )
    parser.add_argument(
        "--once", action="store_true", help="stop everything once the cluster is up and printed"
    )
    parser.add_argument("--keep", action="store_true", help="keep the folder of logs and configs")
    return parser


def _lease(text: str) -> float:
    """``--lease``: seconds etcd can hold a lease for (it counts whole seconds, at least ~1.5)."""
    try:
        seconds = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"lease must be a number of seconds, not {text!r}") from None
    if not MIN_LEASE <= seconds <= MAX_LEASE:
        raise argparse.ArgumentTypeError(f"lease must be from {MIN_LEASE:g} to {MAX_LEASE:g} seconds")
    return seconds


async def run(args: argparse.Namespace) -> int:
    """Start the cluster, print it, wait for Ctrl-C (unless ``--once``), stop it; the exit status."""
    binary = shutil.which("etcd")
    if binary is None:
        print(f"error: {ETCD_MISSING}", file=sys.stderr)
        return 2
    folder = Path(tempfile.mkdtemp(prefix="ps-cluster-"))
    cluster = Cluster(folder, args)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    status = 0
    try:
        starting = asyncio.ensure_future(_start(cluster, binary))
        stopping = asyncio.ensure_future(stop.wait())
        await asyncio.wait((starting, stopping), return_when=asyncio.FIRST_COMPLETED)
        if not starting.done():
            starting.cancel()
            await asyncio.gather(starting, return_exceptions=True)
            return 0
        stopping.cancel()
        starting.result()
        ownership = await cluster.ownership()
        print_owners(ownership, cluster.folder)
        if args.picture is not None:
            args.picture.write_text(draw_owners(ownership))
            print(f"picture of who owns what: {args.picture}")
        pids = " ".join(f"{c.what.replace(' ', '-')}={c.pid}" for c in cluster.children)
        print(f"processes: {pids}")
        if not args.once:
            print("cluster ready; Ctrl-C stops everything", flush=True)
            status = await watch(cluster, stop)
    except (RuntimeError, OSError, grpc.aio.AioRpcError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        status = 1
    finally:
        cluster.stop()
        print("stopped", flush=True)
        if args.keep or (status and cluster.children):  # with nothing started, no logs to keep
            print(f"logs and configs kept in {folder}", file=sys.stderr)
        else:
            shutil.rmtree(folder, ignore_errors=True)
    return status


#: Seconds between looks at whether the processes started still run.
WATCH_PERIOD = 0.5
#: Seconds after the lease that the others get to take a dead gateway's devices over.
TAKEOVER_SLACK = 2.0


async def watch(cluster: Cluster, stop: asyncio.Event) -> int:
    """Until ``stop``: name each process that ends; after a gateway's end, print the owners again.

    Returns 0 when stopped, 1 when no gateway is left (``stop`` is then set too).
    """
    gone: set[int] = set()
    while not stop.is_set():
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), WATCH_PERIOD)
        if stop.is_set():
            return 0
        ended = [c for c in cluster.children if c.pid not in gone and c.proc.poll() is not None]
        for child in ended:
            gone.add(child.pid)
            tail = "\n".join("    " + line for line in child.output().splitlines()[-5:])
            print(f"{child.what} (pid {child.pid}) exited with status {child.proc.returncode}; its log ends:")
            print(tail, flush=True)
            if child.what == "etcd":
                print(
                    "the gateways go on serving what they own and forward to, read-only "
                    "(docs/scale-out.md); Ctrl-C stops everything",
                    flush=True,
                )
        if not any(c.what in {g.id for g in cluster.gateways} for c in ended):
            continue
        if not cluster.live_gateways():
            print("no gateway is left: stopping", flush=True)
            stop.set()
            return 1
        wait = cluster.args.lease + TAKEOVER_SLACK
        print(f"waiting {wait:g} s for the others to take its devices over", flush=True)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), wait)
        if stop.is_set():
            return 0
        try:
            print_owners(await cluster.ownership(), cluster.folder)
        except (RuntimeError, grpc.aio.AioRpcError) as exc:
            print(f"who owns what cannot be read now: {exc}", flush=True)
        sys.stdout.flush()
    return 0


async def _start(cluster: Cluster, binary: str) -> None:
    await cluster.start_etcd(binary)
    await cluster.start_gateways()
    await cluster.start_devices()
    await cluster.wait_listed()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m gateway.cluster``."""
    return asyncio.run(run(_parser().parse_args(argv)))
