"""One grpc.aio channel per remote gateway, shared by every gRPC proxy that reaches it.

A gateway of a cluster forwards every service owned by another gateway through a gRPC proxy
(docs/scale-out.md): with 10,000 devices on 4 gateways, each gateway holds about 7,500 of them
towards 3 owners. A grpc.aio channel of its own for each costs about 15 KiB of memory once
connected (grpc core shares the TCP connection of channels made alike, not the channel), and
each proxy asked the owner for its type and watched the channel's connectivity on its own. So
the proxies take their channel from a :class:`ChannelPool`: one :class:`SharedChannel` per
:class:`ChannelKey` (the remote's address, its TLS files, the channel's settings), reference
counted: made by the first proxy that needs it, closed when the last one lets it go. A channel
to a gateway that died is closed once every service forwarded to it has moved to its new owner
(or left); the ``grpc://`` services of a federation that name one remote gateway share one too.

What each proxy did per service, the shared channel does once per remote gateway:

* **being connected**: :meth:`SharedChannel.wait_ready` is one watch of the channel's
  connectivity, however many proxies wait for it;
* **types**: :attr:`SharedChannel.types` (:class:`~gateway.proxies.remote_types.RemoteTypes`) asks
  the remote registry for the types of many services in one Get.

grpc.aio channels belong to the event loop they were made in: :func:`channel_pool` is the pool of
the running loop.
"""

from __future__ import annotations

import asyncio
import weakref
from dataclasses import dataclass
from typing import Any

import grpc

from gateway.proxies.remote_types import RemoteTypes
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.errors import Unavailable

__all__ = ["ChannelKey", "ChannelPool", "SharedChannel", "TlsFiles", "channel_pool"]


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """The PEM contents a ``grpcs://`` channel is made with; compared by content, so that services
    naming the same files (or copies of them) share a channel."""

    #: The CA that signs the remote's certificate; None: the system's roots.
    ca: bytes | None = None
    #: This gateway's client certificate and its key, for a remote that asks for mutual TLS.
    cert: bytes | None = None
    key: bytes | None = None

    def credentials(self) -> grpc.ChannelCredentials:
        """The channel credentials these files make."""
        return grpc.ssl_channel_credentials(
            root_certificates=self.ca, private_key=self.key, certificate_chain=self.cert
        )


@dataclass(frozen=True, slots=True)
class ChannelKey:
    """What makes two proxies' channels the same channel."""

    #: ``host:port`` of the remote gateway.
    target: str
    #: TLS to it (``grpcs://``); None: plaintext.
    tls: TlsFiles | None
    #: grpc channel arguments (reconnection backoff), as (name, value) pairs.
    settings: tuple[tuple[str, int], ...]
    #: Seconds a query the channel makes for its proxies (the types) may take.
    timeout: float


class SharedChannel:
    """One grpc.aio channel and its stub, shared by ``users`` proxies (see the module docstring)."""

    def __init__(self, key: ChannelKey) -> None:
        self.key = key
        options = list(key.settings)
        if key.tls is None:
            self.channel = grpc.aio.insecure_channel(key.target, options=options)
        else:
            self.channel = grpc.aio.secure_channel(key.target, key.tls.credentials(), options=options)
        #: The PropertyService stub every user calls through.
        self.stub: Any = pb_grpc.PropertyServiceStub(self.channel)
        #: The types of the remote's services, asked in batches.
        self.types = RemoteTypes(self.stub, key.target, key.timeout)
        #: Proxies holding the channel now (:meth:`ChannelPool.acquire` / :meth:`ChannelPool.release`).
        self.users = 0
        self._readiness: asyncio.Task[None] | None = None
        self.closed = False

    def __repr__(self) -> str:
        return f"SharedChannel({self.key.target!r}, users={self.users})"

    async def wait_ready(self) -> None:
        """Wait until the channel is connected to the remote gateway; Unavailable when it is closed
        first. However many wait, the channel's state is watched once; a caller that stops
        waiting (cancelled, timed out) leaves the watch to the others."""
        if self.closed:
            raise Unavailable(f"the channel to gateway {self.key.target} is closed")
        if self.channel.get_state(try_to_connect=True) is grpc.ChannelConnectivity.READY:
            return
        watch = self._readiness
        if watch is None or watch.done():
            watch = self._readiness = asyncio.get_running_loop().create_task(
                self.channel.channel_ready(), name=f"channel to {self.key.target}: ready"
            )
        await asyncio.wait((watch,))
        if watch.cancelled() or watch.exception() is not None:
            raise Unavailable(f"the channel to gateway {self.key.target} is closed")

    async def aclose(self) -> None:
        """Close the channel (its calls end CANCELLED); whoever waits gets Unavailable."""
        if self.closed:
            return
        self.closed = True
        watch, self._readiness = self._readiness, None
        if watch is not None:
            watch.cancel()
            await asyncio.gather(watch, return_exceptions=True)
        await self.types.aclose()
        await self.channel.close(None)


class ChannelPool:
    """The shared channels of one event loop, by :class:`ChannelKey`, reference counted."""

    def __init__(self) -> None:
        self._channels: dict[ChannelKey, SharedChannel] = {}

    def acquire(self, key: ChannelKey) -> SharedChannel:
        """The channel of ``key`` (made now when none is open), counted as used once more."""
        shared = self._channels.get(key)
        if shared is None:
            shared = self._channels[key] = SharedChannel(key)
        shared.users += 1
        return shared

    async def release(self, shared: SharedChannel) -> None:
        """One user of ``shared`` lets it go: the last one closes it (once per :meth:`acquire`)."""
        if shared.users <= 0:
            raise RuntimeError(f"{shared!r} released more often than acquired")
        shared.users -= 1
        if shared.users:
            return
        if self._channels.get(shared.key) is shared:
            del self._channels[shared.key]  # before the close: an acquire meanwhile makes a new one
        await shared.aclose()

    def __len__(self) -> int:
        """Channels open now."""
        return len(self._channels)

    def channels(self) -> list[SharedChannel]:
        """The channels open now."""
        return list(self._channels.values())

    @property
    def users(self) -> int:
        """Proxies holding a channel now, all channels together."""
        return sum(shared.users for shared in self._channels.values())


#: Each event loop's pool; it goes with its loop.
_POOLS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, ChannelPool] = weakref.WeakKeyDictionary()


def channel_pool() -> ChannelPool:
    """The pool of the running event loop (made when first asked for)."""
    loop = asyncio.get_running_loop()
    pool = _POOLS.get(loop)
    if pool is None:
        pool = _POOLS[loop] = ChannelPool()
    return pool
