"""The proxy for ``grpc://HOST:PORT/SERVICE``: a service on another gateway, through the same v1 contract.

``grpcs://HOST:PORT/SERVICE`` is the same over TLS, with options ``ca`` (PEM CA file that signs the
remote gateway's certificate; default: the system's roots) and ``cert`` and ``key`` (this gateway's
client certificate, for a remote that asks for mutual TLS).

Federation: gateway A serves ``far1 = grpc://b:50051/scout1`` and its clients
reach ``scout1`` of gateway B as if it were local. The proxy

* calls through a grpc.aio channel to the remote gateway shared with every other
  proxy that reaches it alike (:mod:`gateway.proxies.grpc_channels`: one per
  address, TLS files and settings, reference counted); Get and Set are unary
  calls under the per-call timeout (a binary value travels in ``data`` both
  ways, and so do Listen events), and the remote's status codes come back
  1:1 as :class:`~services.kernel.errors.PropertyError` with the remote's message,
  prefixed by which remote said it;
* holds one remote Listen (``updates_only``) per (path, parameters), shared
  by all its local listeners (reference counted, :mod:`services.kernel.sharing`); a listen returns only once
  the remote's ``sync`` marker arrived, so no change falls between the
  caller's subscribe and its Get;
* re-opens a broken remote Listen (the remote gateway restarted) with
  exponential backoff (bounded, with jitter), then reads the current value
  and hands it to every listener as a ``Change(gap=True)``;
* learns the service's type from the remote ``registry`` (best effort), asked
  together with the other services of that remote in one Get
  (:mod:`gateway.proxies.remote_types`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

import grpc
from grpc.aio import EOF  # type: ignore[attr-defined]  # missing from grpc-stubs

from gateway.federation import outgoing
from gateway.fronts.grpc_v1.status import error_from_remote
from gateway.options import Wording, option, read_options, url_options
from gateway.proxies.grpc_channels import ChannelKey, ChannelPool, SharedChannel, TlsFiles, channel_pool
from gateway.wire_values import put, received
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.backend import (
    NO_PARAMS,
    UNKNOWN_TYPE,
    Backend,
    BackendInfo,
    Change,
    Notify,
    Subscription,
)
from services.kernel.errors import Code, DeadlineExceeded, InvalidArgument, PropertyError, Unavailable
from services.kernel.model import ServiceModel
from services.kernel.model_codec import model_from_proto
from services.kernel.paths import validate_service_name
from services.kernel.sharing import SharedListen, SharedListens
from services.kernel.values import Value

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class GrpcProxyOptions:
    """Tuning of a ``grpc://`` proxy, set in the config's ``options`` or in the URL's query."""

    #: Seconds a call (and the opening of a remote Listen) may take before DEADLINE_EXCEEDED.
    timeout: float = option(5.0, above=True, unit="seconds")
    #: Seconds a connection attempt to the remote gateway may take.
    connect_timeout: float = option(5.0, above=True, unit="seconds")
    #: First and longest wait between attempts to re-open a broken Listen (and to reconnect the
    #: channel); doubled per failure, with jitter.
    backoff_initial: float = option(0.2, above=True, unit="seconds")
    backoff_max: float = option(10.0, above=True, unit="seconds")

    @classmethod
    def parse(cls, url: str, options: Mapping[str, Any]) -> GrpcProxyOptions:
        """Options from the URL's query, overridden by ``options``; InvalidArgument for a bad one.

        The TLS files (``ca``, ``cert``, ``key``) are left to :func:`tls_files`.
        """
        values, problems = read_options(cls, url_options(url, options), _WORDING, text=True, skip=TLS_OPTIONS)
        if problems:
            raise InvalidArgument("; ".join(problems))
        parsed = cls(**values)
        if parsed.backoff_initial > parsed.backoff_max:
            raise InvalidArgument(
                f"bad grpc proxy options: backoff_initial={parsed.backoff_initial:g} "
                f"is longer than backoff_max={parsed.backoff_max:g}"
            )
        return parsed


_WORDING = Wording(
    unknown="unknown grpc proxy option {key!r} (known: {known})",
    bad="bad grpc proxy option {key}={raw}: {why}",
)

#: The options of a ``grpcs://`` proxy that name files: the CA, the client certificate, its key.
TLS_OPTIONS = ("ca", "cert", "key")


def tls_files(url: str, options: Mapping[str, Any]) -> TlsFiles | None:
    """The TLS files of a ``grpcs://`` URL (None for ``grpc://``), read now.

    InvalidArgument when a file cannot be read, when ``cert`` comes without ``key``, or when a
    ``grpc://`` URL names TLS files.
    """
    merged = url_options(url, options)
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
    return TlsFiles(ca=read.get("ca"), cert=read.get("cert"), key=read.get("key"))


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
        tls: TlsFiles | None = None,
        pool: ChannelPool | None = None,
    ) -> None:
        """``tls``: TLS to the remote gateway (``grpcs://``); None = plaintext. ``pool``: where the
        channel is taken from; None: the running event loop's (:func:`channel_pool`)."""
        self.name = name
        self.url = url
        #: ``host:port`` of the remote gateway.
        self.target = target
        #: The service's name on the remote gateway.
        self.remote = remote
        self.options = options
        self.info = BackendInfo(type=UNKNOWN_TYPE, url=url)  # until reached
        self._key = ChannelKey(
            target,
            tls,
            (
                # gRPC's own reconnection follows the proxy's backoff (its defaults wait up to 2 min);
                # gRPC core takes its "min reconnect backoff" as the time a connection attempt may take.
                ("grpc.initial_reconnect_backoff_ms", _ms(options.backoff_initial)),
                ("grpc.min_reconnect_backoff_ms", _ms(options.connect_timeout)),
                ("grpc.max_reconnect_backoff_ms", _ms(options.backoff_max)),
            ),
            options.timeout,
        )
        self._pool = pool
        #: The shared channel, taken when first needed, given back by :meth:`aclose`.
        self._channel: SharedChannel | None = None
        #: The remote Listens, one per (path, parameters), shared by the proxy's listeners.
        self.shared_listens: SharedListens[_RemoteListen] = SharedListens(
            _RemoteListen, self._open_shared, self._close_shared
        )
        self._type_known = False
        #: The last question for the type to the remote registry (answered in a batch).
        self._learning: asyncio.Future[str] | None = None
        self._closed = False

    def __repr__(self) -> str:
        return f"GrpcProxy({self.name!r}, {self.url!r})"

    def _label(self) -> str:
        return f"{self.remote} on gateway {self.target}"

    # -- lifecycle ---------------------------------------------------------

    def _shared(self) -> SharedChannel:
        """The shared channel to the remote gateway, taken from the pool when first needed."""
        if self._closed:
            raise Unavailable(f"{self._label()}: the proxy is closed")
        if self._channel is None:
            if self._pool is None:
                self._pool = channel_pool()
            self._channel = self._pool.acquire(self._key)
        return self._channel

    def _get_stub(self) -> Any:
        return self._shared().stub

    async def start(self) -> None:
        """Take the channel and ask the remote registry for the type in the background; never waits."""
        self._shared()
        if self._learning is None:
            self._ask_type()

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        entries = self.shared_listens.clear()
        tasks = [entry.follower for entry in entries if entry.follower is not None]
        for entry in entries:
            if entry.call is not None:
                entry.call.cancel()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        # Its own calls are cancelled above; a Get or Set still on its way ends by itself (its
        # timeout), the channel being others' too. The last proxy to let it go closes it.
        shared, self._channel = self._channel, None
        if shared is not None and self._pool is not None:
            await self._pool.release(shared)

    async def wait_connected(self, wait_s: float) -> None:
        """Wait until the remote gateway is reachable (registration); Unavailable after ``wait_s``."""
        shared = self._shared()
        try:
            async with asyncio.timeout(wait_s):
                await shared.wait_ready()
                await self._type_learned()
                if not self._type_known:  # its registry did not know it yet: ask again now
                    self._ask_type()
                    await self._type_learned()
        except TimeoutError:
            raise Unavailable(f"{self._label()}: not reachable within {wait_s:g} s") from None

    def _ask_type(self) -> None:
        """Ask the remote registry for ``services.<SERVICE>.type`` (in its channel's next batch)."""
        learning = self._shared().types.ask(self.remote)
        self._learning = learning
        learning.add_done_callback(self._take_type)

    async def _type_learned(self) -> None:
        """Wait for the answer to the last question for the type, if one is on its way."""
        learning = self._learning
        if learning is None:
            return
        if not learning.done():
            await asyncio.wait((learning,))
        self._take_type(learning)

    def _take_type(self, learning: asyncio.Future[str]) -> None:
        """Take the remote registry's answer (called once it is there; again changes nothing)."""
        if self._type_known or learning.cancelled():
            return
        error = learning.exception()
        if isinstance(error, PropertyError):
            log.debug("%s: no type from its registry: %s", self._label(), error.message)
            # Asked again (by check() and wait_connected()): a remote that could not be reached,
            # and one whose registry does not know the service yet (in a cluster, the owner has
            # published the registration and is still opening its device).
            if error.code not in (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED, Code.NOT_FOUND):
                self._type_known = True
                self.info.type = "resource"  # reached, but its registry does not say what it is
            return
        if error is not None:
            return
        # "unknown": the remote has not heard from the service's device yet (in a cluster, the
        # owner that is still connecting to it): asked again by check() and wait_connected().
        value = learning.result()
        if value and value != UNKNOWN_TYPE:
            self.info.type = value
            self._type_known = True

    # -- calls -------------------------------------------------------------

    def _error(self, exc: grpc.aio.AioRpcError) -> PropertyError:
        return error_from_remote(exc, self._label(), self.options.timeout)

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
            self._ask_type()
            await self._type_learned()

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
        tls = tls_files(url, options)
    except InvalidArgument as exc:
        raise InvalidArgument(f"service {name!r}: {exc.message}") from None
    return GrpcProxy(name, url, target, remote, parsed, tls=tls)
