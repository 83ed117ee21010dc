"""The proxy for ``grpc://HOST:PORT/SERVICE``: a service on another gateway, through the same v1 contract.

``grpcs://HOST:PORT/SERVICE`` is the same over TLS, with options ``ca`` (PEM CA file that signs the
remote gateway's certificate; default: the system's roots) and ``cert`` and ``key`` (this gateway's
client certificate, for a remote that asks for mutual TLS).

Federation: gateway A serves ``far1 = grpc://b:50051/scout1`` and its clients
reach ``scout1`` of gateway B as if it were local. The proxy

* keeps one grpc.aio channel to the remote gateway; Get and Set are unary
  calls under the per-call timeout (a binary value travels in ``data`` both
  ways, and so do Listen events), and the remote's status codes come back
  1:1 as :class:`~services.errors.PropertyError` with the remote's message,
  prefixed by which remote said it;
* holds one remote Listen (``updates_only``) per (path, parameters), shared
  by all its local listeners (reference counted, :mod:`services.sharing`); a listen returns only once
  the remote's ``sync`` marker arrived, so no change falls between the
  caller's subscribe and its Get;
* re-opens a broken remote Listen (the remote gateway restarted) with
  exponential backoff (bounded, with jitter), then reads the current value
  and hands it to every listener as a ``Change(gap=True)``;
* learns the service's type from the remote ``registry`` (best effort).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, unquote, urlsplit

import grpc
from grpc.aio import EOF  # type: ignore[attr-defined]  # missing from grpc-stubs

from gateway.federation import outgoing
from gateway.status import error_from_status
from gateway.wire_values import put, received
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.backend import NO_PARAMS, UNKNOWN_TYPE, Backend, BackendInfo, Change, Notify, Subscription
from services.errors import Code, DeadlineExceeded, InvalidArgument, PropertyError, Unavailable
from services.model import ServiceModel
from services.model_codec import model_from_proto
from services.paths import validate_service_name
from services.sharing import SharedListen, SharedListens
from services.values import Value

log = logging.getLogger(__name__)

#: The name a gateway serves its registry under (``gateway.config.REGISTRY_NAME``), asked for the type.
REMOTE_REGISTRY = "registry"
#: Longest remote message passed on; the rest is cut (a remote is not trusted to be brief).
MAX_REMOTE_MESSAGE = 1000


@dataclass(frozen=True, slots=True)
class GrpcProxyOptions:
    """Tuning of a ``grpc://`` proxy, set in the config's ``options`` or in the URL's query."""

    #: Seconds a call (and the opening of a remote Listen) may take before DEADLINE_EXCEEDED.
    timeout: float = 5.0
    #: Seconds a connection attempt to the remote gateway may take.
    connect_timeout: float = 5.0
    #: First and longest wait between attempts to re-open a broken Listen (and to reconnect the
    #: channel); doubled per failure, with jitter.
    backoff_initial: float = 0.2
    backoff_max: float = 10.0

    @classmethod
    def parse(cls, url: str, options: Mapping[str, Any]) -> GrpcProxyOptions:
        """Options from the URL's query, overridden by ``options``; InvalidArgument for a bad one.

        The TLS files (``ca``, ``cert``, ``key``) are left to :func:`tls_credentials`.
        """
        merged: dict[str, Any] = dict(parse_qsl(urlsplit(url).query))
        merged.update(options)
        for key in TLS_OPTIONS:
            merged.pop(key, None)
        known = {f.name for f in fields(cls)}
        values: dict[str, float] = {}
        for key, raw in merged.items():
            if key not in known:
                raise InvalidArgument(
                    f"unknown grpc proxy option {key!r} (known: {', '.join(sorted(known))})"
                )
            try:
                number = float(raw)
            except (TypeError, ValueError):
                raise InvalidArgument(f"bad grpc proxy option {key}={raw!r}: expected seconds") from None
            if not number > 0 or number == float("inf"):
                raise InvalidArgument(f"bad grpc proxy option {key}={raw!r}: must be a positive number")
            values[key] = number
        parsed = cls(**values)
        if parsed.backoff_initial > parsed.backoff_max:
            raise InvalidArgument(
                f"bad grpc proxy options: backoff_initial={parsed.backoff_initial:g} "
                f"is longer than backoff_max={parsed.backoff_max:g}"
            )
        return parsed


#: The options of a ``grpcs://`` proxy that name files: the CA, the client certificate, its key.
TLS_OPTIONS = ("ca", "cert", "key")


def tls_credentials(url: str, options: Mapping[str, Any]) -> grpc.ChannelCredentials | None:
    """The channel credentials of a ``grpcs://`` URL (None for ``grpc://``), files read now.

    InvalidArgument when a file cannot be read, when ``cert`` comes without ``key``, or when a
    ``grpc://`` URL names TLS files.
    """
    merged: dict[str, Any] = dict(parse_qsl(urlsplit(url).query))
    merged.update(options)
    files = {key: merged[key] for key in TLS_OPTIONS if merged.get(key)}
    if urlsplit(url).scheme != SECURE_SCHEME:
        if files:
            raise InvalidArgument(f"grpc proxy options {', '.join(files)} need TLS: use grpcs://")
        return None
    if ("cert" in files) != ("key" in files):
        raise InvalidArgument("grpcs proxy: a client certificate needs its key: give both cert and key")
    read: dict[str, bytes] = {}
    for key, name in files.items():
        if not isinstance(name, str):
            raise InvalidArgument(f"grpcs proxy option {key}: expected a file name, got {name!r}")
        try:
            read[key] = Path(name).expanduser().read_bytes()
        except OSError as exc:
            raise InvalidArgument(f"grpcs proxy option {key}: cannot read {name!r}: {exc.strerror}") from None
    return grpc.ssl_channel_credentials(
        root_certificates=read.get("ca"), private_key=read.get("key"), certificate_chain=read.get("cert")
    )


def _ms(seconds: float) -> int:
    return max(1, round(seconds * 1000))


class _RemoteListen(SharedListen):
    """One remote Listen shared by every local listener of (path, parameters)."""

    def __init__(self, path: str, params: Mapping[str, str]) -> None:
        super().__init__(path, params)
        self.call: Any = None
        self.follower: asyncio.Task[None] | None = None


class GrpcProxy(Backend):
    """A service on another gateway, reached through the v1 contract (see the module docstring)."""

    def __init__(
        self,
        name: str,
        url: str,
        target: str,
        remote: str,
        options: GrpcProxyOptions,
        *,
        credentials: grpc.ChannelCredentials | None = None,
    ) -> None:
        """``credentials``: TLS to the remote gateway (``grpcs://``); None = plaintext."""
        self.name = name
        self._credentials = credentials
        self.url = url
        #: ``host:port`` of the remote gateway.
        self.target = target
        #: The service's name on the remote gateway.
        self.remote = remote
        self.options = options
        self.info = BackendInfo(type=UNKNOWN_TYPE, url=url)  # until reached
        self._channel: grpc.aio.Channel | None = None
        self._stub: Any = None
        #: The remote Listens, one per (path, parameters), shared by the proxy's listeners.
        self.shared_listens: SharedListens[_RemoteListen] = SharedListens(
            _RemoteListen, self._open_shared, self._close_shared
        )
        self._type_known = False
        self._learning: asyncio.Task[None] | None = None
        self._closed = False

    def __repr__(self) -> str:
        return f"GrpcProxy({self.name!r}, {self.url!r})"

    def _label(self) -> str:
        return f"{self.remote} on gateway {self.target}"

    # -- lifecycle ---------------------------------------------------------

    def _get_stub(self) -> Any:
        if self._closed:
            raise Unavailable(f"{self._label()}: the proxy is closed")
        if self._stub is None:
            channel_options = [
                # gRPC's own reconnection follows the proxy's backoff (its defaults wait up to 2 min);
                # gRPC core takes its "min reconnect backoff" as the time a connection attempt may take.
                ("grpc.initial_reconnect_backoff_ms", _ms(self.options.backoff_initial)),
                ("grpc.min_reconnect_backoff_ms", _ms(self.options.connect_timeout)),
                ("grpc.max_reconnect_backoff_ms", _ms(self.options.backoff_max)),
            ]
            if self._credentials is not None:
                self._channel = grpc.aio.secure_channel(
                    self.target, self._credentials, options=channel_options
                )
            else:
                self._channel = grpc.aio.insecure_channel(self.target, options=channel_options)
            self._stub = pb_grpc.PropertyServiceStub(self._channel)
        return self._stub

    async def start(self) -> None:
        """Make the channel and ask the remote registry for the type in the background; never waits long."""
        self._get_stub()
        if self._learning is None:
            self._learning = asyncio.create_task(self._learn_type(), name=f"grpc proxy {self.name}: type")

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        entries = self.shared_listens.clear()
        tasks = [entry.follower for entry in entries if entry.follower is not None]
        if self._learning is not None:
            tasks.append(self._learning)
        for entry in entries:
            if entry.call is not None:
                entry.call.cancel()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        channel, self._channel, self._stub = self._channel, None, None
        if channel is not None:
            await channel.close(None)

    async def wait_connected(self, wait_s: float) -> None:
        """Wait until the remote gateway is reachable (registration); Unavailable after ``wait_s``."""
        self._get_stub()
        channel = self._channel
        assert channel is not None
        try:
            async with asyncio.timeout(wait_s):
                await channel.channel_ready()
                await self._type_learned()
                if not self._type_known:  # its registry did not know it yet: ask again now
                    await self._learn_type()
        except TimeoutError:
            raise Unavailable(f"{self._label()}: not reachable within {wait_s:g} s") from None

    async def _type_learned(self) -> None:
        learning = self._learning
        if learning is not None and not learning.done():
            await asyncio.shield(learning)

    async def _learn_type(self) -> None:
        """Take ``services.<SERVICE>.type`` from the remote registry; nothing when it cannot be read."""
        try:
            reply = await self._get_stub().Get(
                pb.GetRequest(service=REMOTE_REGISTRY, property=f"services.{self.remote}.type"),
                timeout=self.options.timeout,
                metadata=outgoing(),
            )
        except grpc.aio.AioRpcError as exc:
            log.debug("%s: no type from its registry: %s", self._label(), exc.details())
            # Only a remote that could not be reached is asked again (by check()).
            if exc.code() not in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                self._type_known = True
                self.info.type = "resource"  # reached, but its registry does not say what it is
            return
        # "unknown": the remote has not heard from the service's device yet (in a cluster, the
        # owner that is still connecting to it): asked again by check() and wait_connected().
        if reply.value and reply.value != UNKNOWN_TYPE:
            self.info.type = reply.value
            self._type_known = True

    # -- calls -------------------------------------------------------------

    def _error(self, exc: grpc.aio.AioRpcError) -> PropertyError:
        status = exc.code()
        details = (exc.details() or status.name)[:MAX_REMOTE_MESSAGE]
        if (
            status is grpc.StatusCode.DEADLINE_EXCEEDED and details == "Deadline Exceeded"
        ):  # our own deadline, not the remote's
            details = f"no answer within {self.options.timeout:g} s"
        return error_from_status(status, f"{self._label()}: {details}")

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        await self._type_learned()
        request = pb.GetRequest(service=self.remote, property=path, parameters=dict(params))
        try:
            reply = await self._get_stub().Get(request, timeout=self.options.timeout, metadata=outgoing())
        except grpc.aio.AioRpcError as exc:
            raise self._error(exc) from None
        return received(reply)

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        await self._type_learned()
        request = pb.SetRequest(service=self.remote, property=path, parameters=dict(params))
        put(request, value)
        try:
            reply = await self._get_stub().Set(request, timeout=self.options.timeout, metadata=outgoing())
        except grpc.aio.AioRpcError as exc:
            raise self._error(exc) from None
        return received(reply)

    async def describe(self) -> ServiceModel:
        """The remote service's model, from the remote gateway's Describe (names only from an older one)."""
        await self._type_learned()
        request = pb.DescribeRequest(service=self.remote)
        try:
            reply = await self._get_stub().Describe(
                request, timeout=self.options.timeout, metadata=outgoing()
            )
        except grpc.aio.AioRpcError as exc:
            if exc.code() is grpc.StatusCode.UNIMPLEMENTED:
                return await super().describe()
            raise self._error(exc) from None
        model = model_from_proto(reply)
        return model if model.type else replace(model, type=self.info.type)

    async def check(self) -> None:
        """Alive when the remote service answers a Get of ``properties`` within the timeout.

        Also learns the type from the remote registry while it is not known
        (the remote was down when the proxy started).
        """
        await self.get("properties")
        if not self._type_known:
            await self._learn_type()

    # -- listening ---------------------------------------------------------

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        await self._type_learned()
        return await self.shared_listens.listen(path, notify, params)

    async def _open_shared(self, shared: _RemoteListen) -> None:
        shared.call = await self._open_remote(shared)
        if self._closed:  # closed while the remote Listen was being opened
            shared.call.cancel()
            raise Unavailable(f"{self._label()}: the proxy is closed")
        shared.follower = asyncio.create_task(
            self._follow(shared), name=f"grpc proxy {self.name}.{shared.path}"
        )

    def _listen_request(self, shared: _RemoteListen) -> pb.ListenRequest:
        return pb.ListenRequest(
            service=self.remote,
            property=shared.path,
            parameters=shared.params,
            options=pb.ListenOptions(updates_only=True),
        )

    async def _open_remote(self, shared: _RemoteListen) -> Any:
        """Open a remote Listen and read up to its ``sync`` marker; the call, ready to be followed."""
        call = self._get_stub().Listen(self._listen_request(shared), metadata=outgoing())
        try:
            async with asyncio.timeout(self.options.timeout):
                while True:
                    response = await call.read()
                    if response is EOF:
                        raise Unavailable(f"{self._label()}: the remote ended the Listen of {shared.path}")
                    self._forward(shared, response)
                    if response.sync:
                        return call
        except grpc.aio.AioRpcError as exc:
            call.cancel()
            raise self._error(exc) from None
        except TimeoutError:
            call.cancel()
            raise DeadlineExceeded(
                f"{self._label()}: Listen of {shared.path} not ready within {self.options.timeout:g} s"
            ) from None
        except BaseException:
            call.cancel()
            raise

    def _forward(self, shared: _RemoteListen, response: pb.ListenResponse) -> None:
        for event in response.events:
            value = event.data if event.HasField("data") else event.value
            shared.deliver(Change(shared.path, value, gap=event.gap, removed=event.removed))

    async def _follow(self, shared: _RemoteListen) -> None:
        """Read the remote Listen; when it breaks, open it again with backoff and report a gap."""
        failures = 0
        while self.shared_listens.holds(shared):
            call = shared.call
            try:
                while (response := await call.read()) is not EOF:
                    self._forward(shared, response)
                reason = "the remote ended the stream"
            except grpc.aio.AioRpcError as exc:
                reason = self._error(exc).message
            call.cancel()
            shared.call = None
            log.warning("%s: Listen of %s broke (%s); opening it again", self._label(), shared.path, reason)
            while self.shared_listens.holds(shared):
                failures += 1
                delay = min(
                    self.options.backoff_max, self.options.backoff_initial * 2 ** min(failures - 1, 30)
                )
                await asyncio.sleep(delay * random.uniform(0.5, 1.0))
                try:
                    value = await self._reopen(shared)
                except PropertyError as exc:
                    if exc.code is Code.NOT_FOUND:
                        self.shared_listens.drop(shared)
                        shared.deliver(Change(shared.path, "", removed=True))
                        return
                    # Said once per outage; every further attempt only at DEBUG.
                    level = logging.INFO if failures == 1 else logging.DEBUG
                    log.log(level, "cannot listen to %s again yet: %s", shared.path, exc.message)
                    continue
                failures = 0
                log.info("%s: listening to %s again", self._label(), shared.path)
                shared.deliver(Change(shared.path, value, gap=True))
                break

    async def _reopen(self, shared: _RemoteListen) -> Value:
        """Open the remote Listen again, then read the current value (the caller reports it as a gap)."""
        call = await self._open_remote(shared)
        try:
            value = await self.get(shared.path, shared.params)
        except BaseException:
            call.cancel()
            raise
        shared.call = call
        return value

    async def _close_shared(self, shared: _RemoteListen) -> None:
        if shared.call is not None:
            shared.call.cancel()
            shared.call = None
        follower = shared.follower
        if follower is not None and follower is not asyncio.current_task():
            follower.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await follower


#: The scheme of a proxy over TLS.
SECURE_SCHEME = "grpcs"


def open_grpc_backend(name: str, url: str, options: Mapping[str, Any]) -> Backend:
    """The factory for ``grpc://HOST:PORT[/SERVICE][?option=value...]`` and ``grpcs://`` (not started).

    SERVICE is the service's name on the remote gateway; without it, ``name``.
    """
    expected = f"expected grpc://HOST:PORT/SERVICE or grpcs://HOST:PORT/SERVICE (got {url[:200]!r})"
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = None
    if (
        parts.scheme not in ("grpc", SECURE_SCHEME)
        or not parts.hostname
        or not port
        or parts.username
        or parts.fragment
    ):
        raise InvalidArgument(f"service {name!r}: bad URL: {expected}")
    remote = unquote(parts.path.strip("/")) or name
    try:
        validate_service_name(remote)
    except InvalidArgument as exc:
        raise InvalidArgument(
            f"service {name!r}: bad remote service in URL: {exc.message}; {expected}"
        ) from None
    host = parts.hostname
    target = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    parsed = GrpcProxyOptions.parse(url, options)
    try:
        credentials = tls_credentials(url, options)
    except InvalidArgument as exc:
        raise InvalidArgument(f"service {name!r}: {exc.message}") from None
    return GrpcProxy(name, url, target, remote, parsed, credentials=credentials)
