"""The gateway's TOML configuration (documented in ``docs/configuration.md``).

:func:`load_config` reads a file, :func:`parse_config` a parsed mapping, and
:func:`default_config` the embedded demo (``gateway/demo.toml``). Every
mistake — an unknown key, a wrong type, a duplicate or bad service name —
raises :class:`ConfigError` naming the file and the key.
"""

from __future__ import annotations

import importlib.resources
import ipaddress
import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

from gateway.audit import AuditSection
from gateway.engine.identity import Authenticator, AuthSection
from gateway.engine.rules import Rule
from gateway.logs import LOG_FORMATS
from gateway.options import Wording, convert, option, read_options, shown
from gateway.stores.address import parse_store_url
from gateway.stores.etcd import DEFAULT_LEASE as DEFAULT_STORE_LEASE
from gateway.stores.etcd import DEFAULT_PREFIX as DEFAULT_STORE_PREFIX
from gateway.stores.etcd import MAX_LEASE as MAX_STORE_LEASE
from gateway.stores.etcd import MIN_LEASE as MIN_STORE_LEASE
from services.apps.registry import (
    DEFAULT_ALLOW,
    DEFAULT_MAX_LICENCE_DURATION,
    DEFAULT_MAX_LICENCES,
    DEFAULT_MAX_LICENCES_PER_HOLDER,
    DEFAULT_MAX_REGISTRATIONS,
    parse_allow_entry,
)
from services.apps.registry.lease import MAX_LEASE
from services.apps.registry.scheduling import DEFAULT_MAX_QUEUED, DEFAULT_TOUT, DEFAULT_TR, check_capabilities
from services.kernel.errors import InvalidArgument, PropertyError
from services.kernel.paths import WILDCARD, validate_pattern, validate_service_name

#: The service every gateway hosts itself; a config may not define it.
REGISTRY_NAME = "registry"
DEFAULT_LISTEN = "127.0.0.1:50051"

_T = TypeVar("_T")


class ConfigError(Exception):
    """The configuration is wrong: each of ``problems`` names the file and the key (the message lists all)."""

    def __init__(self, *problems: str) -> None:
        super().__init__("\n".join(problems))
        self.problems: tuple[str, ...] = problems


class _Problems:
    """Every problem of one config, so that one run of check-config reports them all."""

    def __init__(self) -> None:
        self.found: list[str] = []

    def attempt(self, check: Callable[[], _T], instead: _T) -> _T:
        """``check()``, or ``instead`` when it raises ConfigError (whose problems are kept)."""
        try:
            return check()
        except ConfigError as exc:
            self.found.extend(exc.problems)
            return instead


@dataclass(frozen=True, slots=True)
class GatewaySection:
    """``[gateway]``: where to listen and how to behave."""

    #: host:port of the gRPC server; port 0 picks a free port.
    listen: str = DEFAULT_LISTEN
    #: host:port of the raw-TCP line-protocol listener; empty = off.
    line_listen: str = ""
    #: Seconds any one backend call may take before DEADLINE_EXCEEDED.
    call_timeout: float = option(5.0, above=True, unit="seconds")
    log_level: str = "info"
    #: How log lines look: "text" (time level logger: message) or "json" (one object a line).
    log_format: str = "text"
    #: Seconds Listen and Session streams get to end at shutdown.
    shutdown_grace: float = option(2.0, unit="seconds")
    #: Listen on a non-loopback address without TLS (anyone who reaches the port reads and drives
    #: every service); false = such a config is refused.
    allow_insecure_remote: bool = False
    #: gRPC connections open at once (grpc.max_allowed_incoming_connections); beyond, a new one is
    #: closed as soon as it is accepted. Its share of open files (docs/security.md, "Bounded
    #: connections").
    max_connections: int = option(4096, low=1)
    #: Seconds a gRPC connection with no call running may stay open (grpc.max_connection_idle_ms).
    idle_timeout: float = option(300.0, above=True, unit="seconds")
    #: Seconds a new connection gets to finish its TLS handshake and HTTP/2 preface (gRPC) or its TLS
    #: handshake (HTTPS); a connection that sends nothing is closed after it.
    handshake_timeout: float = option(10.0, above=True, unit="seconds")
    #: Seconds each ``[[devices]]`` process may take to say where it serves, at start and at each
    #: restart; a process still silent after it is ended and the gateway's start fails.
    device_start_timeout: float = option(30.0, above=True, unit="seconds")


@dataclass(frozen=True, slots=True)
class LineTlsSection:
    """``[tls.line]``: TLS on the line-protocol listener (devices that can do it)."""

    #: PEM certificate chain and private key of the listener; both or neither.
    cert: str = ""
    key: str = ""
    #: PEM CA certificates; when given, a device must present a certificate signed by one of them.
    client_ca: str = ""

    @property
    def enabled(self) -> bool:
        """True when the line listener speaks TLS."""
        return bool(self.cert)


@dataclass(frozen=True, slots=True)
class TlsSection:
    """``[tls]``: TLS, and mutual TLS, on the gRPC port.

    File names are relative to the config file's folder (absolute once parsed). The files are read
    again when the gateway gets SIGHUP; open streams keep their connection.
    """

    #: PEM certificate chain and private key of the server; both or neither.
    cert: str = ""
    key: str = ""
    #: PEM CA certificates that sign client certificates.
    client_ca: str = ""
    #: Refuse a client without a certificate signed by ``client_ca`` (mutual TLS).
    require_client_cert: bool = False
    line: LineTlsSection = field(default_factory=LineTlsSection)

    @property
    def enabled(self) -> bool:
        """True when the gRPC port speaks TLS."""
        return bool(self.cert)


@dataclass(frozen=True, slots=True)
class Limits:
    """``[limits]``: bounds that keep one client from exhausting the gateway."""

    #: Selectors in one Listen request (the request's own plus ``more``).
    max_selectors: int = option(64, low=1)
    #: Properties one Listen stream may match after wildcards are expanded.
    max_stream_properties: int = option(10_000, low=1)
    #: Listen streams open at once, gRPC Listen and Session listens together.
    max_streams: int = option(10_000, low=1)
    #: Paths in one Get (the request's own plus ``more``).
    max_get_paths: int = option(1_000, low=1)
    #: Events in one ListenResponse when the client does not ask for fewer.
    max_batch: int = option(256, low=1)
    #: Get and Set requests running at once in one Session; beyond, reading waits.
    session_max_in_flight: int = option(256, low=1)
    #: Replies waiting to be written in one Session; beyond, reading waits.
    session_max_queued_replies: int = option(1024, low=1)
    #: Smallest min_interval, sample_interval or heartbeat_interval accepted (seconds).
    min_interval_floor: float = option(0.001, unit="seconds")
    #: Seconds a line-listener connection may stay silent (nothing read, nothing written) before
    #: it is closed; and when the listener is full, the connection silent longest makes room.
    line_idle_timeout: float = option(300.0, above=True, unit="seconds")
    #: Devices dialled in to the line listener from one source address served at once.
    max_greetings_per_source: int = option(64, low=1)
    #: Line-listener connections open at once (devices and clients); when full, the connection
    #: silent longest makes room for a new one.
    line_max_connections: int = option(1024, low=1)
    #: Line-listener connections from one address at once; beyond, that address's connection
    #: silent longest makes room (a flood from one address cannot lock out a device beside it).
    line_max_connections_per_address: int = option(128, low=1)
    #: Unary calls (Get, Set, Describe) running at once on the gRPC port; beyond, RESOURCE_EXHAUSTED
    #: naming this limit. grpc's queue of calls not yet taken up holds at least 20,000 more.
    max_calls: int = option(10_000, low=1)
    #: Bytes of large values (64 KiB or more: binary ones) handed to Listen readers, event and
    #: image streams and not yet taken by their connections, all readers together; a reader whose
    #: next value would pass it ends with RESOURCE_EXHAUSTED (gateway.engine.listen.budget). A stalled
    #: reader holds at most one value (two copies of it on gRPC), so 256 MiB is about 65 readers
    #: stalled at once on 4 MB camera frames, or 1,300 on 200 KB ones.
    max_pending_binary: int = option(256 * 1024 * 1024, low=1)


#: Bytes of a request body the HTTP front end reads at most (a Set's JSON); beyond, 413. A value
#: text is at most 64 KiB (services.kernel.values.MAX_VALUE_LENGTH); 1 MiB leaves room for JSON escapes
#: (up to 6 bytes a character) and parameters, and is nginx's default client_max_body_size.
DEFAULT_HTTP_MAX_BODY = 1024 * 1024


@dataclass(frozen=True, slots=True)
class HttpSection:
    """``[http]``: the HTTP/JSON and Server-Sent-Events front end, and the browser console it serves."""

    #: host:port of the HTTP front end; port 0 picks a free port; empty = no HTTP front end.
    listen: str = ""
    #: Serve the static browser console (``gateway/console/``) at ``/``.
    console: bool = True
    #: Most bytes of a JSON request body; beyond, 413 (a binary property's raw bytes are bounded
    #: by its own ``max_size`` instead).
    max_body: int = option(DEFAULT_HTTP_MAX_BODY, low=1)
    #: Server-Sent-Events and live image streams open at once; beyond, 503. An idle event stream
    #: costs about 13 KiB of gateway memory (bench/sse.py, docs/performance.md), so 4,096 of them
    #: about 52 MiB.
    max_streams: int = option(4096, low=1)
    #: Server-Sent-Events and live image streams one client address may hold at once; beyond,
    #: 429 (one client cannot take every place).
    max_streams_per_client: int = option(64, low=1)
    #: Seconds one write to an event stream may wait for the client to read; beyond, the
    #: stream ends (a client that reads nothing for that long is gone).
    write_timeout: float = option(30.0, above=True, unit="seconds")
    #: Seconds between heartbeat comments on an idle event stream.
    heartbeat: float = option(15.0, unit="seconds")
    #: Serve HTTPS with the ``[tls]`` section's certificate (and client CA).
    tls: bool = False
    #: Connections open at once, event streams and plain requests together; beyond, a new one is
    #: answered 503 and closed at once. Its share of open files (docs/security.md).
    max_connections: int = option(6144, low=1)
    #: Connections one client address may hold open at once; beyond, 503 and closed at once.
    max_connections_per_address: int = option(256, low=1)
    #: Seconds a connection may stay open with no request running (a fresh one that sends
    #: nothing, or a kept-alive one between requests); an event stream is a running request.
    idle_timeout: float = option(60.0, above=True, unit="seconds")
    #: Origins besides the front end's own whose pages may open its WebSockets (the Foxglove
    #: endpoint), e.g. ``["https://app.foxglove.dev"]``; every other route keeps to its own origin.
    websocket_origins: tuple[str, ...] = ()


#: Picture files a floor plan may be (``[console] map_image``), by suffix: what a browser draws
#: in an SVG ``<image>``, with the content type the HTTP front end serves it as.
MAP_IMAGE_TYPES = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".gif": "image/gif",
    ".webp": "image/webp",
    ".svg": "image/svg+xml",
}


@dataclass(frozen=True, slots=True)
class ConsoleSection:
    """``[console]``: what the browser console shows beyond the gateway's services (docs/console.md)."""

    #: A floor-plan picture drawn under the map's robots (PNG, JPEG, GIF, WebP or SVG); empty = none.
    #: A relative path is taken from the config file's folder (absolute once parsed).
    map_image: str = ""
    #: Where the picture lies on the plane, metres: ``[x0, y0, x1, y1]``, its lower left (south-west)
    #: and upper right (north-east) corners.
    map_extent: tuple[float, ...] = ()


#: Connections the ``[metrics] listen`` port holds at once, and from one address: a scraper or
#: two beside the gateway need a handful (its share of open files, docs/security.md).
METRICS_MAX_CONNECTIONS = 64
METRICS_MAX_CONNECTIONS_PER_ADDRESS = 16


@dataclass(frozen=True, slots=True)
class MetricsSection:
    """``[metrics]``: the Prometheus endpoint (docs/metrics.md)."""

    #: Count calls, streams and events, and serve ``/metrics`` on the HTTP front end (when it is on).
    enabled: bool = True
    #: host:port of a plain-HTTP listener of its own serving only ``/metrics``; empty = none.
    #: Like the HTTP front end, a plaintext address off loopback needs ``allow_insecure_remote``.
    listen: str = ""


@dataclass(frozen=True, slots=True)
class HistorySection:
    """``[history]``: the changes of which properties the gateway keeps in memory for the History
    call (docs/recording.md, "History"); off when no selector is given."""

    #: ``SERVICE/PATH`` selectors of the properties kept, ``*`` standing for the service or for a
    #: path segment as in a Listen (``["*/location", "scout1/battery"]``); empty = no history.
    selectors: tuple[str, ...] = ()
    #: Changes kept per property (its latest ones).
    size: int = option(1000, low=1)
    #: Keep binary values too (camera frames fill the bounds in seconds: off unless asked).
    binary: bool = False
    #: Changes kept of all properties together; past it, the oldest change of all goes first.
    max_entries: int = option(1_000_000, low=1)
    #: Bytes of kept values (and 256 a change besides: what a change costs, measured) of all
    #: properties together; past it, the oldest change of all goes first. 64 MiB holds about
    #: 250,000 changes of short values, so for those it is reached before ``max_entries``.
    max_bytes: int = option(64 * 1024 * 1024, low=1)
    #: Events a History call answers when it asks for no fewer (its ``limit`` 0).
    default_limit: int = option(1000, low=1)
    #: Events a History call answers at most, whatever it asks (a message stays under 4 MiB too).
    max_limit: int = option(10_000, low=1)
    #: A folder of recordings (the recorder's) that answers for the time before the rings
    #: reach; empty = the rings only.
    recordings: str = ""


#: Devices a gateway hands over at once when it rebalances: each is a connection closed, a claim and
#: a connection opened; a few dozen keep one round short and the other gateways' work small.
DEFAULT_REBALANCE_BATCH = 32
#: Devices owned beyond the least-loaded gateway that a gateway keeps without rebalancing.
DEFAULT_REBALANCE_SPREAD = 2


@dataclass(frozen=True, slots=True)
class RegistrySection:
    """``[registry]``: liveness checks of the services and where run-time registrations are kept."""

    #: Seconds between liveness checks of each service outside the gateway; 0 = no checks.
    period: float = option(5.0, unit="seconds")
    #: Seconds a service gets to answer one check.
    timeout: float = option(2.0, above=True, unit="seconds")
    #: Checks missed in a row before the service is ``down`` (its calls get UNAVAILABLE).
    misses: int = option(3, low=1)
    #: Seconds a service registered at run time may stay ``down`` before it is removed.
    grace: float = option(60.0, unit="seconds")
    #: JSON file keeping the registrations made by Set across restarts; empty = not kept.
    #: A relative path is taken from the config file's folder (absolute once parsed).
    persist: str = ""
    #: The scheduler: longest allocation in seconds (the seed's ``Tout``; at most the longest
    #: licence), longest wait of a queued request (``Tr``), requests waiting at once.
    tout: float = option(DEFAULT_TOUT, above=True, unit="seconds")
    tr: float = option(DEFAULT_TR, above=True, unit="seconds")
    max_queued: int = option(DEFAULT_MAX_QUEUED, low=1)
    #: Addresses a registration may reach: networks with optional ports, serial path globs
    #: (``services.apps.registry.allow``); default: loopback and USB serial adapters.
    allow: tuple[str, ...] = DEFAULT_ALLOW
    #: Registrations by Set held at once.
    max_registrations: int = option(DEFAULT_MAX_REGISTRATIONS, low=1)
    #: Licences held at once (``acquire``); one more is RESOURCE_EXHAUSTED.
    max_licences: int = option(DEFAULT_MAX_LICENCES, low=1)
    #: Licences one holder may hold when it acquires one; one more is RESOURCE_EXHAUSTED.
    max_licences_per_holder: int = option(DEFAULT_MAX_LICENCES_PER_HOLDER, low=1)
    #: Longest licence in seconds (a longer ``duration`` is INVALID_ARGUMENT); a longer job renews.
    max_licence_duration: float = option(
        DEFAULT_MAX_LICENCE_DURATION, above=True, high=MAX_LEASE, unit="seconds"
    )
    #: Where the registry is kept: empty = embedded (this gateway's memory and ``persist``);
    #: ``etcd://HOST:PORT[,HOST:PORT...]`` (``etcds://`` for TLS) = shared by many gateways.
    store: str = ""
    #: PEM files for ``etcds://``: the CA of etcd's certificate, this gateway's client certificate
    #: and key (absolute once parsed; relative paths are taken from the config file's folder).
    store_ca: str = ""
    store_cert: str = ""
    store_key: str = ""
    #: The folder of every key this cluster writes in etcd.
    store_prefix: str = DEFAULT_STORE_PREFIX
    #: Seconds of this gateway's lease in etcd (kept alive every third of it): a gateway that dies
    #: loses what it owned within this time.
    store_lease: float = option(
        DEFAULT_STORE_LEASE, low=MIN_STORE_LEASE, high=MAX_STORE_LEASE, unit="seconds"
    )
    #: This gateway's id in the cluster; empty = made from the host name and the gRPC port.
    gateway_id: str = ""
    #: host:port the other gateways dial to reach this gateway's services; empty = the gRPC
    #: listen address.
    advertise: str = ""
    #: PEM files for forwarding calls to gateways of the cluster that serve TLS: the CA that
    #: signs their certificates (empty = the system's roots), and this gateway's client
    #: certificate and key for those that require one (``[tls] require_client_cert``).
    peer_ca: str = ""
    peer_cert: str = ""
    peer_key: str = ""
    #: Rebalance by policy: when a gateway joins, returns or is undrained, the gateways that own
    #: more than ``rebalance_spread`` devices beyond it hand some over, ``rebalance_batch`` at a
    #: time (docs/scale-out.md, "Operating a cluster"). Off: only an admin's ``cluster.rebalance``.
    rebalance: bool = False
    rebalance_spread: int = DEFAULT_REBALANCE_SPREAD
    rebalance_batch: int = option(DEFAULT_REBALANCE_BATCH, low=1)


#: Seconds a woken dormant service stays unused before it is stopped again, by default.
DEFAULT_IDLE_STOP = 60.0


@dataclass(frozen=True, slots=True)
class ServiceEntry:
    """One ``[[services]]`` entry: an in-process service (``type``) or a proxy (``url``)."""

    name: str
    type: str = ""
    url: str = ""
    options: Mapping[str, Any] = field(default_factory=dict)
    #: Capabilities it offers the registry's scheduler, beside its type (``["survey", "video"]``).
    features: tuple[str, ...] = ()
    #: A device that dials in (``url = "tcp-in://"``): the file holding the secret its greeting
    #: must carry (``secret=...``); absolute once parsed. Nobody else may take its name.
    secret_file: str = ""
    #: Declared but not started: the gateway starts it when a call (or the registry's ``wake``)
    #: needs it, and stops it again after ``idle_stop`` seconds without use.
    dormant: bool = False
    #: Seconds a woken dormant service may stay unused before it is stopped; 0 = never stopped.
    idle_stop: float = DEFAULT_IDLE_STOP

    @property
    def dials_in(self) -> bool:
        """A device that dials in to the line listener, not a backend the gateway opens."""
        return self.url.startswith(f"{DIAL_IN_SCHEME}:")


#: URL scheme of a configured device that dials in to the line listener.
DIAL_IN_SCHEME = "tcp-in"

#: The one value ``[[devices]] serial`` takes: a pseudo-terminal the device process creates.
PTY = "pty"


@dataclass(frozen=True, slots=True)
class DeviceEntry:
    """One ``[[devices]]`` entry: a Python stand-in for a microcontroller.

    The gateway starts it as a child process
    (``python -m services.device ... --exit-with-parent``), on raw TCP
    (``tcp``) or on a pseudo-terminal (``serial = "pty"``), serves it as
    service ``name`` through the tcp:// or serial:// proxy, and ends it at
    shutdown.
    """

    name: str
    type: str
    #: host:port the device listens on (port 0 = a free port); empty when on a serial line.
    tcp: str = ""
    #: "pty" for a pseudo-terminal; empty when on TCP.
    serial: str = ""
    #: Baud rate of the serial line.
    baudrate: int = 115200
    #: Handed to ``services.apps.catalog.create(type, **options)`` in the device process.
    options: Mapping[str, Any] = field(default_factory=dict)
    #: Handed to the proxy (timeout, keepalive, ...), as for a ``[[services]]`` url.
    proxy: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Config:
    """A whole, checked configuration."""

    gateway: GatewaySection = field(default_factory=GatewaySection)
    limits: Limits = field(default_factory=Limits)
    registry: RegistrySection = field(default_factory=RegistrySection)
    tls: TlsSection = field(default_factory=TlsSection)
    #: ``[http]``: the HTTP/JSON + SSE front end (off unless ``listen`` is set).
    http: HttpSection = field(default_factory=HttpSection)
    services: tuple[ServiceEntry, ...] = ()
    devices: tuple[DeviceEntry, ...] = ()
    #: ``[auth]``: how bearer tokens are checked (docs/security.md, "Identity").
    auth: AuthSection = field(default_factory=AuthSection)
    #: ``[[rules]]``: who may do what (docs/security.md, "Rules"); none = everything is allowed.
    rules: tuple[Rule, ...] = ()
    #: ``[audit]``: how many audit lines may be written (docs/security.md, "Audit").
    audit: AuditSection = field(default_factory=AuditSection)
    #: ``[metrics]``: the Prometheus endpoint (docs/metrics.md).
    metrics: MetricsSection = field(default_factory=MetricsSection)
    #: ``[history]``: the properties whose changes are kept (docs/recording.md, "History").
    history: HistorySection = field(default_factory=HistorySection)
    #: ``[console]``: the browser console's floor plan (docs/console.md).
    console: ConsoleSection = field(default_factory=ConsoleSection)
    #: Where it came from, for messages.
    source: str = "<config>"

    def with_overrides(
        self,
        *,
        listen: str | None = None,
        log_level: str | None = None,
        http: str | None = None,
        log_format: str | None = None,
    ) -> Config:
        """A copy with command-line overrides applied (``http=""`` turns the HTTP front end off)."""
        gw = self.gateway
        if listen is not None:
            gw = replace(gw, listen=_check_address(listen, f"{self.source}: --listen"))
            _check_exposure(gw, self.tls, f"{self.source}: --listen")
        if log_level is not None:
            gw = replace(gw, log_level=_check_log_level(log_level, f"{self.source}: --log-level"))
        if log_format is not None:
            gw = replace(gw, log_format=_check_log_format(log_format, f"{self.source}: --log-format"))
        web = self.http
        if http is not None:
            if http:
                _check_address(http, f"{self.source}: --http")
            web = replace(web, listen=http)
            _check_http_exposure(web, gw, self.tls, f"{self.source}: --http")
        return replace(self, gateway=gw, http=web)


_LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
#: How a problem of a config table is said: where it is in the file, what is wrong, what was given.
_IN_A_TABLE = Wording(
    unknown="{where}.{key}: unknown key (known: {known})", bad="{where}.{key}: {why}, got {raw}"
)


def _check_address(value: str, where: str) -> str:
    host, sep, port = value.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"{where}: expected host:port like '127.0.0.1:50051', got {value!r}")
    return value


def _check_log_level(value: str, where: str) -> str:
    if value.lower() not in _LOG_LEVELS:
        raise ConfigError(f"{where}: expected one of {', '.join(_LOG_LEVELS)}, got {value!r}")
    return value.lower()


def _check_log_format(value: str, where: str) -> str:
    if value not in LOG_FORMATS:
        raise ConfigError(f"{where}: expected one of {', '.join(LOG_FORMATS)}, got {value!r}")
    return value


def _typed(value: Any, kind: type, where: str) -> Any:
    try:
        return convert(value, kind)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}, got {shown(value)}") from None


class _PartlyBad(ConfigError):
    """A section with bad keys: ``partial`` is built from its good ones, so later checks still run."""

    def __init__(self, problems: list[str], partial: Any) -> None:
        super().__init__(*problems)
        self.partial = partial


def _section(cls: type[Any], data: Any, where: str, skip: tuple[str, ...] = ()) -> Any:
    """The section as ``cls`` (its fields declare what each key takes, :mod:`gateway.options`);
    raises _PartlyBad naming every bad key (the good ones are kept). ``skip``: keys read apart."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a table")
    values, bad = read_options(cls, data, _IN_A_TABLE, skip=skip, where=where)
    if bad:
        raise _PartlyBad(bad, cls(**values))
    return cls(**values)


def _checked_section(
    cls: type[_T], data: Any, where: str, checks: Callable[[_T, list[str]], _T], skip: tuple[str, ...] = ()
) -> _T:
    """:func:`_section`, then ``checks(section, found)`` (what no one key says alone); every problem
    of the section in one ConfigError."""
    found: list[str] = []
    try:
        section: _T = _section(cls, data, where, skip)
    except _PartlyBad as partly:
        found.extend(partly.problems)
        section = partly.partial
    section = checks(section, found)
    if found:
        raise ConfigError(*found)
    return section


def parse_config(data: Mapping[str, Any], source: str = "<config>", folder: Path | None = None) -> Config:
    """Check a parsed TOML document and build a :class:`Config`; raises ConfigError.

    ``folder`` is where relative paths in it start (the config file's folder;
    default: the current directory).
    """
    config, problems = parse_config_partly(data, source, folder)
    if problems:
        raise ConfigError(*problems)
    return config


def parse_config_partly(
    data: Mapping[str, Any], source: str = "<config>", folder: Path | None = None
) -> tuple[Config, list[str]]:
    """Every problem of a parsed TOML document, and the config its good parts make.

    A bad section falls back to its defaults (with its good keys kept) and a bad
    service or device is left out, so that ``check-config`` can go on to build
    what is left and report every problem of the file in one run.
    """
    top = (
        *("gateway", "limits", "registry", "tls", "http", "services", "devices", "auth", "rules", "audit"),
        "metrics",
        "history",
        "console",
    )
    problems = _Problems()
    for key in data:
        if key not in top:
            problems.found.append(f"{source}: unknown key {key!r} (known: {', '.join(top)})")
    gw: GatewaySection = problems.attempt(
        lambda: _gateway(data.get("gateway", {}), f"{source}: gateway"), GatewaySection()
    )
    limits: Limits = problems.attempt(lambda: _limits(data.get("limits", {}), f"{source}: limits"), Limits())
    registry = problems.attempt(
        lambda: _registry(data.get("registry", {}), f"{source}: registry", folder), RegistrySection()
    )
    tls: TlsSection = problems.attempt(
        lambda: _tls(data.get("tls", {}), f"{source}: tls", folder), TlsSection()
    )
    problems.attempt(lambda: _check_exposure(gw, tls, f"{source}: gateway"), None)
    http: HttpSection = problems.attempt(
        lambda: _http(data.get("http", {}), f"{source}: http", gw, tls, limits), HttpSection()
    )
    seen: set[str] = set()
    services: list[ServiceEntry] = []
    raw_services = data.get("services", [])
    if not isinstance(raw_services, list):
        problems.found.append(f"{source}: services: expected an array of tables ([[services]])")
        raw_services = []
    for i, raw in enumerate(raw_services):
        services += problems.attempt(lambda: [_service(raw, f"{source}: services[{i}]", seen, folder)], [])  # noqa: B023
    devices: list[DeviceEntry] = []
    raw_devices = data.get("devices", [])
    if not isinstance(raw_devices, list):
        problems.found.append(f"{source}: devices: expected an array of tables ([[devices]])")
        raw_devices = []
    for i, raw in enumerate(raw_devices):
        devices += problems.attempt(lambda: [_device(raw, f"{source}: devices[{i}]", seen)], [])  # noqa: B023
    auth = problems.attempt(lambda: _auth(data.get("auth", {}), f"{source}: auth", folder), AuthSection())
    rules: tuple[Rule, ...] = problems.attempt(lambda: _rules(data.get("rules", []), f"{source}: rules"), ())
    audit = problems.attempt(lambda: _section(AuditSection, data.get("audit", {}), f"{source}: audit"), None)
    metrics: MetricsSection = problems.attempt(
        lambda: _metrics(data.get("metrics", {}), f"{source}: metrics", gw), MetricsSection()
    )
    history: HistorySection = problems.attempt(
        lambda: _history(data.get("history", {}), f"{source}: history", folder), HistorySection()
    )
    console: ConsoleSection = problems.attempt(
        lambda: _console(data.get("console", {}), f"{source}: console", folder), ConsoleSection()
    )
    if any(e.dials_in for e in services) and not gw.line_listen:
        problems.found.append(f"{source}: services: a device that dials in needs gateway.line_listen")
    config = Config(
        auth=auth,
        rules=rules,
        audit=audit or AuditSection(),
        metrics=metrics,
        history=history,
        console=console,
        gateway=gw,
        limits=limits,
        registry=registry,
        tls=tls,
        http=http,
        services=tuple(services),
        devices=tuple(devices),
        source=source,
    )
    return config, problems.found


def _gateway(data: Any, where: str) -> GatewaySection:
    def checks(gw: GatewaySection, found: list[str]) -> GatewaySection:
        problems = _Problems()
        problems.attempt(lambda: _check_address(gw.listen, f"{where}.listen"), None)
        if gw.line_listen:
            problems.attempt(lambda: _check_address(gw.line_listen, f"{where}.line_listen"), None)
        level = problems.attempt(lambda: _check_log_level(gw.log_level, f"{where}.log_level"), "info")
        log_format = problems.attempt(lambda: _check_log_format(gw.log_format, f"{where}.log_format"), "text")
        found.extend(problems.found)
        return replace(gw, log_level=level, log_format=log_format)

    return _checked_section(GatewaySection, data, where, checks)


def _config_file(value: str, where: str, folder: Path | None) -> str:
    """An existing file named in the config, as an absolute path (relative: from the config's folder)."""
    path = Path(value).expanduser()
    if not path.is_absolute():
        path = (folder if folder is not None else Path.cwd()) / path
    if not path.is_file():
        raise ConfigError(f"{where}: no such file {str(path)!r}")
    return str(path)


def _tls_files(section: Any, where: str, folder: Path | None) -> Any:
    """``section`` with its cert, key and client_ca files checked and made absolute."""
    if bool(section.cert) != bool(section.key):
        raise ConfigError(
            f"{where}: give both 'cert' and 'key' (the server's certificate and its private key)"
        )
    found = {}
    for key in ("cert", "key", "client_ca"):
        if getattr(section, key):
            found[key] = _config_file(getattr(section, key), f"{where}.{key}", folder)
    if section.client_ca and not section.cert:
        raise ConfigError(f"{where}.client_ca: client certificates need TLS; give 'cert' and 'key' too")
    return replace(section, **found)


def _tls(data: Any, where: str, folder: Path | None) -> TlsSection:
    section: TlsSection = _tls_files(_section(TlsSection, data, where, skip=("line",)), where, folder)
    line: LineTlsSection = _tls_files(
        _section(LineTlsSection, data.get("line", {}), f"{where}.line"), f"{where}.line", folder
    )
    if section.require_client_cert and not section.client_ca:
        raise ConfigError(
            f"{where}.require_client_cert: name the CA that signs client certificates in 'client_ca'"
        )
    return replace(section, line=line)


def is_loopback(address: str) -> bool:
    """True when ``host:port`` (or ``unix:PATH``) can only be reached from this machine."""
    if address.startswith("unix:"):
        return True
    host = address.rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name other than localhost may resolve to anything


def _check_exposure(gw: GatewaySection, tls: TlsSection, where: str) -> None:
    """Refuse a plaintext listener on a non-loopback address unless the config says so explicitly."""
    if gw.allow_insecure_remote:
        return
    exposed = []
    if not is_loopback(gw.listen) and not tls.enabled:
        exposed.append(("listen", gw.listen, "[tls] cert and key"))
    if gw.line_listen and not is_loopback(gw.line_listen) and not tls.line.enabled:
        exposed.append(("line_listen", gw.line_listen, "[tls.line] cert and key"))
    if exposed:
        raise ConfigError(
            *(
                f"{where}.{key}: {address!r} is reachable from other machines and is not encrypted:"
                f" anyone who reaches it can read and drive every service. Give {fix}"
                " (see docs/security.md), listen on 127.0.0.1, or set [gateway] allow_insecure_remote = true"
                " to accept that on a network you trust"
                for key, address, fix in exposed
            )
        )


def _check_http_exposure(http: HttpSection, gw: GatewaySection, tls: TlsSection, where: str) -> None:
    """The HTTP front end is held to the gRPC port's rule: plaintext only on loopback, unless allowed."""
    if not http.listen or gw.allow_insecure_remote or is_loopback(http.listen):
        return
    if http.tls and tls.enabled:
        return
    raise ConfigError(
        f"{where}: {http.listen!r} is reachable from other machines and is not encrypted: anyone who"
        " reaches it can read and drive every service. Set [http] tls = true with [tls] cert and key"
        " (see docs/security.md), listen on 127.0.0.1, or set [gateway] allow_insecure_remote = true"
        " to accept that on a network you trust"
    )


def _origins(value: Any, where: str) -> tuple[str, ...]:
    """Origins as a browser sends them: ``scheme://host`` with an optional port, nothing after."""
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f'{where}: expected an array of origins like ["https://app.foxglove.dev"]')
    for origin in value:
        scheme, sep, rest = origin.partition("://")
        if not sep or not scheme or not rest or "/" in rest:
            raise ConfigError(f"{where}: {origin[:100]!r} is no origin: write scheme://host[:port], no path")
    return tuple(value)


def _console(data: Any, where: str, folder: Path | None) -> ConsoleSection:
    found_before: list[str] = []
    extent: tuple[float, ...] = ()
    if isinstance(data, Mapping) and "map_extent" in data:
        raw = data["map_extent"]
        numbers = raw if isinstance(raw, list) and len(raw) == 4 else None
        if raw == []:
            pass  # none, as when the key is left out
        elif numbers is None or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in numbers
        ):
            found_before.append(
                f"{where}.map_extent: expected four numbers [x0, y0, x1, y1] (metres), got {shown(raw)}"
            )
        elif not (numbers[2] > numbers[0] and numbers[3] > numbers[1]):
            found_before.append(
                f"{where}.map_extent: the upper right corner (x1, y1) must lie right of and above the"
                f" lower left (x0, y0), got {shown(raw)}"
            )
        else:
            extent = tuple(float(v) for v in numbers)

    def checks(section: ConsoleSection, found: list[str]) -> ConsoleSection:
        found.extend(found_before)
        section = replace(section, map_extent=extent)
        if not section.map_image:
            if extent:
                found.append(f"{where}.map_extent: give map_image too (the picture it places)")
            return section
        suffix = Path(section.map_image).suffix.lower()
        if suffix not in MAP_IMAGE_TYPES:
            found.append(
                f"{where}.map_image: {section.map_image[:200]!r} is not a picture the console draws"
                f" (known: {', '.join(MAP_IMAGE_TYPES)})"
            )
            return replace(section, map_image="")
        try:
            section = replace(
                section, map_image=_config_file(section.map_image, f"{where}.map_image", folder)
            )
        except ConfigError as exc:
            found.extend(exc.problems)
            return replace(section, map_image="")
        if not extent and not found_before:
            found.append(f"{where}.map_extent: give where the floor plan lies, [x0, y0, x1, y1] in metres")
        return section

    return _checked_section(ConsoleSection, data, where, checks, skip=("map_extent",))


def _http(data: Any, where: str, gw: GatewaySection, tls: TlsSection, limits: Limits) -> HttpSection:
    found_before: list[str] = []
    origins: tuple[str, ...] = ()
    if isinstance(data, Mapping) and "websocket_origins" in data:
        try:
            origins = _origins(data["websocket_origins"], f"{where}.websocket_origins")
        except ConfigError as exc:
            found_before.extend(exc.problems)

    def checks(http: HttpSection, found: list[str]) -> HttpSection:
        found.extend(found_before)
        http = replace(http, websocket_origins=origins)
        if http.listen:
            try:
                _check_address(http.listen, f"{where}.listen")
            except ConfigError as exc:
                found.extend(exc.problems)
                return replace(http, listen="")
        if http.heartbeat < limits.min_interval_floor:
            found.append(
                f"{where}.heartbeat: must be a number of seconds of at least limits.min_interval_floor"
                f" ({limits.min_interval_floor:g}), got {http.heartbeat!r}"
            )
        if http.tls and not tls.enabled:
            found.append(f"{where}.tls: HTTPS needs the [tls] section's cert and key")
        try:
            _check_http_exposure(http, gw, tls, f"{where}.listen")
        except ConfigError as exc:
            found.extend(exc.problems)
        return http

    return _checked_section(HttpSection, data, where, checks, skip=("websocket_origins",))


def _history(data: Any, where: str, folder: Path | None) -> HistorySection:
    def checks(history: HistorySection, found: list[str]) -> HistorySection:
        raw = data.get("selectors", []) if isinstance(data, Mapping) else []
        if not isinstance(raw, list) or not all(isinstance(text, str) for text in raw):
            found.append(f"{where}.selectors: expected a list of SERVICE/PATH strings, got {shown(raw)}")
            raw = []
        history = replace(history, selectors=tuple(raw))
        for i, text in enumerate(history.selectors):
            service, slash, path = text.partition("/")
            try:
                if not slash or not service or not path:
                    raise InvalidArgument("must be SERVICE/PATH, like scout1/location or */location")
                if service != WILDCARD:
                    validate_service_name(service)
                validate_pattern(path)
            except PropertyError as exc:
                found.append(f"{where}.selectors[{i}]: {exc.message}, got {shown(text)}")
        if history.default_limit > history.max_limit:
            found.append(f"{where}.default_limit: must be at most max_limit ({history.max_limit})")
        if history.recordings:
            recordings = Path(history.recordings).expanduser()
            if not recordings.is_absolute():
                recordings = (folder if folder is not None else Path.cwd()) / recordings
            history = replace(history, recordings=str(recordings))
        return history

    return _checked_section(HistorySection, data, where, checks, skip=("selectors",))


def _metrics(data: Any, where: str, gw: GatewaySection) -> MetricsSection:
    def checks(metrics: MetricsSection, found: list[str]) -> MetricsSection:
        if not metrics.listen:
            return metrics
        try:
            _check_address(metrics.listen, f"{where}.listen")
        except ConfigError as exc:
            found.extend(exc.problems)
            return replace(metrics, listen="")
        if not (gw.allow_insecure_remote or is_loopback(metrics.listen)):
            found.append(
                f"{where}.listen: {metrics.listen!r} is reachable from other machines and is plain HTTP:"
                " anyone who reaches it reads the gateway's counters. Listen on 127.0.0.1, or set"
                " [gateway] allow_insecure_remote = true to accept that on a network you trust"
            )
        return metrics

    return _checked_section(MetricsSection, data, where, checks)


def _limits(data: Any, where: str) -> Limits:
    return _checked_section(Limits, data, where, lambda limits, found: limits)


def _registry(data: Any, where: str, folder: Path | None) -> RegistrySection:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a table")
    found: list[str] = []
    try:
        allow = _allow(data.get("allow", list(DEFAULT_ALLOW)), f"{where}.allow")
    except ConfigError as exc:
        found.extend(exc.problems)
        allow = DEFAULT_ALLOW

    def checks(section: RegistrySection, found_here: list[str]) -> RegistrySection:
        found_here.extend(found)
        section = replace(section, allow=allow)
        section = _store(section, where, folder, found_here)
        if section.persist:
            path = Path(section.persist).expanduser()
            if not path.is_absolute():
                path = (folder if folder is not None else Path.cwd()) / path
            if path.is_dir():
                found_here.append(f"{where}.persist: {str(path)!r} is a folder; name a file")
            section = replace(section, persist=str(path))
        return section

    return _checked_section(RegistrySection, data, where, checks, skip=("allow",))


#: Longest gateway id: it is part of etcd keys and values, and of log lines.
MAX_GATEWAY_ID = 128


def _store(section: RegistrySection, where: str, folder: Path | None, found: list[str]) -> RegistrySection:
    """The ``store*``, ``gateway_id`` and ``advertise`` keys checked; TLS files made absolute."""
    tls = False
    if section.store:
        try:
            tls = parse_store_url(section.store).tls
        except ValueError as e:
            found.append(f"{where}.store: {e}")
        if section.persist:
            found.append(
                f"{where}.persist: keeps the embedded store's registrations; with store = "
                f"{section.store!r} they are kept there: remove one of the two"
            )
    files: dict[str, str] = {}
    for key in ("store_ca", "store_cert", "store_key", "peer_ca", "peer_cert", "peer_key"):
        value = getattr(section, key)
        if not value:
            continue
        if key.startswith("store") and not tls:
            found.append(f"{where}.{key}: TLS files need a store URL starting with etcds://")
            continue
        if key.startswith("peer") and not section.store:
            found.append(f"{where}.{key}: TLS files for the other gateways of a cluster need a store")
            continue
        try:
            files[key] = _config_file(value, f"{where}.{key}", folder)
        except ConfigError as exc:
            found.extend(exc.problems)
    if bool(section.store_cert) != bool(section.store_key):
        found.append(f"{where}: give both 'store_cert' and 'store_key' (this gateway's certificate for etcd)")
    if bool(section.peer_cert) != bool(section.peer_key):
        found.append(
            f"{where}: give both 'peer_cert' and 'peer_key' "
            "(this gateway's client certificate for the other gateways)"
        )
    prefix = section.store_prefix.rstrip("/")
    if not section.store_prefix.startswith("/") or not prefix or any(c.isspace() for c in prefix):
        found.append(
            f"{where}.store_prefix: expected a folder of keys like '/propertyservice', "
            f"got {section.store_prefix!r}"
        )
    gateway_id = section.gateway_id
    if gateway_id and (
        len(gateway_id) > MAX_GATEWAY_ID
        or "/" in gateway_id
        or not gateway_id.isprintable()
        or " " in gateway_id
    ):
        found.append(
            f"{where}.gateway_id: 1 to {MAX_GATEWAY_ID} printable characters without '/' or spaces, "
            f"got {gateway_id[:MAX_GATEWAY_ID]!r}"
        )
    if section.rebalance and not section.store:
        found.append(f"{where}.rebalance: moves devices between the gateways of a cluster: it needs a store")
    if section.advertise:
        try:
            _check_address(section.advertise, f"{where}.advertise")
        except ConfigError as exc:
            found.extend(exc.problems)
    return replace(
        section,
        store_prefix=prefix or section.store_prefix,
        store_ca=files.get("store_ca", section.store_ca),
        store_cert=files.get("store_cert", section.store_cert),
        store_key=files.get("store_key", section.store_key),
        peer_ca=files.get("peer_ca", section.peer_ca),
        peer_cert=files.get("peer_cert", section.peer_cert),
        peer_key=files.get("peer_key", section.peer_key),
    )


def _allow(value: Any, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(
            f'{where}: expected an array of strings like ["127.0.0.0/8", "serial:/dev/ttyUSB*"]'
        )
    for entry in value:
        try:
            parse_allow_entry(entry)
        except InvalidArgument as exc:
            raise ConfigError(f"{where}: {exc.message}") from None
    return tuple(value)


def _auth(data: Any, where: str, folder: Path | None) -> AuthSection:
    section: AuthSection = _section(AuthSection, data, where)
    for key in ("jwt_secret_file", "jwks_file"):
        value = getattr(section, key)
        if value:
            path = Path(value).expanduser()
            if not path.is_absolute():
                path = (folder if folder is not None else Path.cwd()) / path
            section = replace(section, **{key: str(path)})
    try:
        Authenticator(section)  # reads the key files: a bad one is a config error, found at once
    except InvalidArgument as exc:
        raise ConfigError(f"{where[: where.rfind(':')]}: {exc.message}") from None
    return section


_RULE_KEYS = ("subject", "service", "path", "operations", "effect")


def _rules(data: Any, where: str) -> tuple[Rule, ...]:
    if not isinstance(data, list):
        raise ConfigError(f"{where}: expected an array of tables ([[rules]])")
    rules = []
    for index, entry in enumerate(data):
        at = f"{where}[{index}]"
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{at}: expected a table")
        for key in entry:
            if key not in _RULE_KEYS:
                raise ConfigError(f"{at}.{key}: unknown key (known: {', '.join(_RULE_KEYS)})")
        for key in ("subject", "operations", "effect"):
            if key not in entry:
                raise ConfigError(f"{at}: missing key {key!r}")
        operations = entry["operations"]
        if isinstance(operations, str):
            operations = [operations]
        subject = entry["subject"]
        if not isinstance(operations, list) or not all(isinstance(op, str) for op in operations):
            raise ConfigError(f'{at}.operations: expected a list like ["read", "write"]')
        if not isinstance(subject, str | list):
            raise ConfigError(f'{at}.subject: expected a name, "*" or a list of names')
        try:
            rules.append(
                Rule.build(
                    index,
                    subject=subject,
                    service=_typed(entry.get("service", "*"), str, f"{at}.service"),
                    path=_typed(entry.get("path", "**"), str, f"{at}.path"),
                    operations=operations,
                    effect=_typed(entry["effect"], str, f"{at}.effect"),
                )
            )
        except InvalidArgument as exc:
            raise ConfigError(f"{where[: where.rfind(':')]}: {exc.message}") from None
    return tuple(rules)


def _name(entry: Any, where: str, known: tuple[str, ...], seen: set[str]) -> str:
    """Check the keys of a service or device table and its name; the name."""
    if not isinstance(entry, Mapping):
        raise ConfigError(f"{where}: expected a table")
    for key in entry:
        if key not in known:
            raise ConfigError(f"{where}.{key}: unknown key (known: {', '.join(known)})")
    if "name" not in entry:
        raise ConfigError(f"{where}: missing key 'name'")
    name: str = _typed(entry["name"], str, f"{where}.name")
    try:
        validate_service_name(name)
    except InvalidArgument as exc:
        raise ConfigError(f"{where}.name: {exc.message}") from None
    if name == REGISTRY_NAME:
        raise ConfigError(f"{where}.name: {name!r} is reserved: every gateway hosts its own registry")
    if name in seen:
        raise ConfigError(f"{where}.name: duplicate service name {name!r}")
    seen.add(name)
    return name


def _service(entry: Any, where: str, seen: set[str], folder: Path | None = None) -> ServiceEntry:
    name = _name(
        entry,
        where,
        ("name", "type", "url", "options", "secret_file", "dormant", "idle_stop", "features"),
        seen,
    )
    where = f"{where} ({name})"
    kind = _typed(entry.get("type", ""), str, f"{where}.type")
    url = _typed(entry.get("url", ""), str, f"{where}.url")
    if bool(kind) == bool(url):
        raise ConfigError(f"{where}: give exactly one of 'type' (an in-process service) or 'url' (a proxy)")
    if url and "://" not in url:
        raise ConfigError(f"{where}.url: expected scheme://address like 'tcp://127.0.0.1:7001', got {url!r}")
    options = entry.get("options", {})
    if not isinstance(options, Mapping):
        raise ConfigError(f"{where}.options: expected a table like {{ speed = 0.5 }}")
    secret_file = _typed(entry.get("secret_file", ""), str, f"{where}.secret_file")
    features = _features(entry.get("features", []), f"{where}.features")
    service = ServiceEntry(
        name=name, type=kind, url=url, options=_paths_resolved(kind, options, folder), features=features
    )
    service = _dormancy(service, entry, where)
    if service.dials_in or secret_file:
        service = replace(service, secret_file=_secret_file(service, secret_file, where, folder))
    return service


def _features(value: Any, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f'{where}: expected an array of capability names like ["survey", "video"]')
    try:
        return tuple(sorted(check_capabilities(value, "features")))
    except InvalidArgument as exc:
        raise ConfigError(f"{where}: {exc.message}") from None


def _dormancy(service: ServiceEntry, entry: Mapping[str, Any], where: str) -> ServiceEntry:
    """``dormant`` and ``idle_stop`` of a ``[[services]]`` entry, checked."""
    dormant = _typed(entry.get("dormant", False), bool, f"{where}.dormant")
    if dormant and service.dials_in:
        raise ConfigError(f"{where}.dormant: a device that dials in starts itself; it cannot be dormant")
    if "idle_stop" not in entry:
        return replace(service, dormant=dormant)
    if not dormant:
        raise ConfigError(f"{where}.idle_stop: only a dormant service (dormant = true) is stopped when idle")
    idle = entry["idle_stop"]
    if isinstance(idle, bool) or not isinstance(idle, int | float) or not math.isfinite(idle) or idle < 0:
        raise ConfigError(
            f"{where}.idle_stop: must be zero (never stopped) or a number of seconds, got {idle!r}"
        )
    return replace(service, dormant=True, idle_stop=float(idle))


def _paths_resolved(kind: str, options: Mapping[str, Any], folder: Path | None) -> dict[str, Any]:
    """``options`` with the relative paths among them (``services.apps.catalog.PATH_OPTIONS``) taken from
    the config file's folder, as every path in a config is."""
    from services.apps.catalog import PATH_OPTIONS, PATH_TABLE_OPTIONS

    def resolve(value: str) -> str:
        path = Path(value).expanduser()
        if not path.is_absolute():
            path = (folder if folder is not None else Path.cwd()) / path
        return str(path)

    resolved = dict(options)
    for key in PATH_OPTIONS.get(kind, ()):
        value = resolved.get(key)
        if isinstance(value, str) and value:
            resolved[key] = resolve(value)
    for key, other in PATH_TABLE_OPTIONS.get(kind, ()):
        table = resolved.get(key)
        if isinstance(table, Mapping):  # anything else is the service's own error to report
            resolved[key] = {
                name: resolve(v) if isinstance(v, str) and v and not v.startswith(other) else v
                for name, v in table.items()
            }
    return resolved


def _secret_file(service: ServiceEntry, secret_file: str, where: str, folder: Path | None) -> str:
    if not service.dials_in:
        raise ConfigError(f'{where}.secret_file: only a device that dials in (url = "tcp-in://") has one')
    if service.url != f"{DIAL_IN_SCHEME}://" or service.options:
        raise ConfigError(f'{where}.url: a device that dials in is url = "tcp-in://" with no options')
    if not secret_file:
        raise ConfigError(
            f"{where}: a device that dials in needs secret_file (its greeting carries the secret)"
        )
    path = Path(secret_file).expanduser()
    if not path.is_absolute():
        path = (folder if folder is not None else Path.cwd()) / path
    try:
        secret = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{where}.secret_file: cannot read {str(path)!r}: {exc}") from None
    if not secret or any(c.isspace() for c in secret):
        raise ConfigError(f"{where}.secret_file: the secret must be one word with no spaces")
    return str(path)


def _device(entry: Any, where: str, seen: set[str]) -> DeviceEntry:
    from services.apps.catalog import CATALOG, factory_of, needs_directory

    known = ("name", "type", "tcp", "serial", "baudrate", "options", "proxy")
    name = _name(entry, where, known, seen)
    where = f"{where} ({name})"
    if "type" not in entry:
        raise ConfigError(f"{where}: missing key 'type' (one of {', '.join(sorted(CATALOG))})")
    kind = _typed(entry["type"], str, f"{where}.type")
    try:
        factory_of(kind)
    except PropertyError as e:
        raise ConfigError(f"{where}.type: {e.message}") from None
    if needs_directory(kind):
        raise ConfigError(
            f"{where}.type: a {kind!r} reaches other services and runs only inside the gateway;"
            " make it a [[services]] entry"
        )
    tcp = _typed(entry.get("tcp", ""), str, f"{where}.tcp")
    serial = _typed(entry.get("serial", ""), str, f"{where}.serial")
    if bool(tcp) == bool(serial):
        raise ConfigError(f"{where}: give exactly one of 'tcp' (\"127.0.0.1:0\") or 'serial' (\"pty\")")
    if tcp:
        _check_address(tcp, f"{where}.tcp")
    if serial and serial != PTY:
        raise ConfigError(
            f"{where}.serial: only {PTY!r} (a pseudo-terminal the device creates) is supported,"
            f" got {serial!r};"
            ' for a device on a real serial port use a [[services]] entry with url = "serial:///dev/..."'
        )
    baudrate = _typed(entry.get("baudrate", 115200), int, f"{where}.baudrate")
    if baudrate <= 0:
        raise ConfigError(f"{where}.baudrate: must be positive, got {baudrate}")
    tables = {}
    for key in ("options", "proxy"):
        value = entry.get(key, {})
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}.{key}: expected a table like {{ speed = 0.5 }}")
        tables[key] = dict(value)
    return DeviceEntry(
        name=name,
        type=kind,
        tcp=tcp,
        serial=serial,
        baudrate=baudrate,
        options=tables["options"],
        proxy=tables["proxy"],
    )


def load_config(path: str | Path) -> Config:
    """Read and check the TOML file at ``path``; raises ConfigError."""
    config, problems = load_config_partly(path)
    if problems or config is None:
        raise ConfigError(*problems)
    return config


def load_config_partly(path: str | Path) -> tuple[Config | None, list[str]]:
    """Read the TOML file at ``path``: every problem, and the config its good parts make
    (None when the file cannot be read or is not TOML); see :func:`parse_config_partly`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        return None, [f"{p}: cannot read: {exc.strerror or exc}"]
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return None, [f"{p}: not valid TOML: {exc}"]
    return parse_config_partly(data, str(p), p.resolve().parent)


def loads_config(text: str, source: str = "<config>", folder: Path | None = None) -> Config:
    """Parse and check TOML text; raises ConfigError. ``folder``: see :func:`parse_config`."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    return parse_config(data, source, folder)


def default_config() -> Config:
    """The embedded demo configuration (``gateway/demo.toml``)."""
    text = importlib.resources.files("gateway").joinpath("demo.toml").read_text(encoding="utf-8")
    return loads_config(text, "demo.toml (built in)")
