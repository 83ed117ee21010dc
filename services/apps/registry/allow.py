"""Which addresses a registration may make the gateway reach: the ``[registry] allow`` list.

A registration by Set makes the gateway open a connection on the caller's
behalf. Unchecked, that turns the gateway into a port scanner and a relay to
any host it can reach, or a thief of the serial lines its own devices use.
Every registration URL is therefore checked here, *before* any connection is
made, and refused with PERMISSION_DENIED with the same message whether the
port behind it is open or closed.

Syntax of one entry (docs/registry-and-groups.md, "Who may be registered"):

* ``"127.0.0.0/8"``, ``"10.1.2.3"``, ``"::1"``, ``"fd00::/8"`` — an address
  or network, any port (``tcp://`` and ``grpc://`` URLs);
* ``"10.0.0.0/8:7000-7100"``, ``"192.168.1.5:7001"``, ``"[fd00::/8]:7000-7100"``
  — the same with one port or an inclusive range of ports;
* ``"serial:/dev/ttyUSB*"`` — a glob of serial device paths (``fnmatch``).

Host names in a URL are resolved (never connected to): every address a name
resolves to must be allowed. The serial path of a device the gateway's own
config serves is never registrable again, whatever the list says.
"""

from __future__ import annotations

import asyncio
import fnmatch
import ipaddress
import os
import socket
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

from services.kernel.errors import InvalidArgument, PermissionDenied

__all__ = ["DEFAULT_ALLOW", "AddressRule", "AllowList", "parse_allow_entry"]

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network

#: The default: loopback only, and the usual USB serial adapters. Pseudo-terminals
#: (``/dev/pts/*``) are not on it: those are how the gateway's own device processes talk.
DEFAULT_ALLOW: tuple[str, ...] = ("127.0.0.0/8", "::1", "serial:/dev/ttyUSB*", "serial:/dev/ttyACM*")

_SERIAL_PREFIX = "serial:"


@dataclass(frozen=True, slots=True)
class AddressRule:
    """One network with an inclusive port range (1-65535 when the entry named none)."""

    network: IPNetwork
    first_port: int = 1
    last_port: int = 65535

    def admits(self, address: ipaddress.IPv4Address | ipaddress.IPv6Address, port: int) -> bool:
        """``address:port`` falls inside this rule."""
        return address in self.network and self.first_port <= port <= self.last_port


def _ports(text: str, entry: str) -> tuple[int, int]:
    first, dash, last = text.partition("-")
    if not first.isdigit() or (dash and not last.isdigit()):
        raise InvalidArgument(f"allow entry {entry!r}: expected a port or a range like 7000-7100")
    low, high = int(first), int(last) if dash else int(first)
    if not 1 <= low <= high <= 65535:
        raise InvalidArgument(f"allow entry {entry!r}: ports must be 1-65535, low to high")
    return low, high


def parse_allow_entry(entry: str) -> AddressRule | str:
    """One entry of the list: an :class:`AddressRule`, or a serial path glob (a str); InvalidArgument."""
    text = entry.strip()
    if text.startswith(_SERIAL_PREFIX):
        pattern = text[len(_SERIAL_PREFIX) :]
        if not pattern.startswith("/"):
            raise InvalidArgument(f"allow entry {entry!r}: a serial pattern is an absolute path glob")
        return pattern
    host, ports = text, ""
    if text.startswith("["):  # [v6 network]:ports
        host, close, rest = text[1:].partition("]")
        if not close or (rest and not rest.startswith(":")):
            raise InvalidArgument(f"allow entry {entry!r}: expected [ADDRESS/PREFIX]:PORTS")
        ports = rest[1:]
    elif text.count(":") == 1:  # v4 network:ports (a bare v6 address has several colons)
        host, _, ports = text.partition(":")
    try:
        network = ipaddress.ip_network(host, strict=False)
    except ValueError:
        raise InvalidArgument(
            f"allow entry {entry!r}: expected an address or network (10.0.0.0/8, ::1), "
            "optionally with :PORT or :LOW-HIGH, or serial:/dev/GLOB"
        ) from None
    low, high = _ports(ports, entry) if ports else (1, 65535)
    return AddressRule(network, low, high)


def _is_local_address(address: str) -> bool:
    """This machine owns ``address`` (binding to it works); binding connects to nothing."""
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((address, 0))
    except OSError:
        return False
    return True


class AllowList:
    """The ``[registry] allow`` list, and the addresses that are the gateway itself.

    ``own_ports()`` gives the ports the gateway listens on (its gRPC port and
    its line listener): a URL naming one of them on an address of this
    machine would make the gateway call itself, a loop refused with
    INVALID_ARGUMENT. ``reserved_paths`` are the serial lines of the
    configured devices (more are added with :meth:`reserve` as devices start).
    """

    def __init__(
        self,
        entries: Iterable[str] = DEFAULT_ALLOW,
        *,
        own_ports: Callable[[], Sequence[int]] = tuple,
        reserved_paths: Iterable[str] = (),
    ) -> None:
        self.entries = tuple(entries)
        parsed = [parse_allow_entry(e) for e in self.entries]
        self.rules = tuple(r for r in parsed if isinstance(r, AddressRule))
        self.serial_globs = tuple(r for r in parsed if isinstance(r, str))
        self.reserved_paths: set[str] = set()
        for path in reserved_paths:
            self.reserve(path)
        self._own_ports = own_ports

    def reserve(self, path: str) -> None:
        """Never let a registration open the serial line ``path`` (a configured device's)."""
        self.reserved_paths.update({path, os.path.realpath(path)})

    async def check(self, name: str, url: str) -> None:
        """Refuse ``url`` unless it is allowed; connects to nothing (names are only resolved).

        Raises PermissionDenied (not on the list, or a configured device's
        serial line) and InvalidArgument (the gateway itself).
        """
        parts = urlsplit(url)
        if parts.scheme == "serial":
            self._check_serial(name, parts.path)
            return
        host, port = parts.hostname or "", parts.port or 0
        addresses = await self._resolve(name, host, port)
        own = set(self._own_ports())
        for address in addresses:
            if port in own and (
                address.is_loopback or address.is_unspecified or _is_local_address(str(address))
            ):
                raise InvalidArgument(
                    f"registering {name!r}: {url[:120]} is this gateway itself; "
                    "a service that calls itself would loop until the deadline"
                )
        for address in addresses:
            if not any(rule.admits(address, port) for rule in self.rules):
                raise self._refused(name, url)

    def _refused(self, name: str, url: str) -> PermissionDenied:
        # The same words whether or not anything listens there: no probing through the registry.
        return PermissionDenied(
            f"registering {name!r}: {url[:120]} is not on the gateway's [registry] allow list "
            f"({', '.join(self.entries) or 'empty'}); nothing was contacted"
        )

    def _check_serial(self, name: str, path: str) -> None:
        real = os.path.realpath(path)
        if real in self.reserved_paths or path in self.reserved_paths:
            raise PermissionDenied(
                f"registering {name!r}: serial:{path[:120]} is the line of a device this gateway's "
                "config serves; it cannot be registered again"
            )
        if not any(fnmatch.fnmatchcase(path, g) and fnmatch.fnmatchcase(real, g) for g in self.serial_globs):
            raise self._refused(name, f"serial://{path}")

    async def _resolve(
        self, name: str, host: str, port: int
    ) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
        try:
            return [ipaddress.ip_address(host)]
        except ValueError:
            pass
        try:
            infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError:
            raise InvalidArgument(
                f"registering {name!r}: cannot resolve the host name {host[:80]!r}"
            ) from None
        found = {ipaddress.ip_address(str(info[4][0]).partition("%")[0]) for info in infos}
        return sorted(found, key=str)
