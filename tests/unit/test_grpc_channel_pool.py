"""gRPC proxies share one channel per remote gateway: counted, closed with its last user, and one
watch and one batch of type queries for all its proxies, against a real gateway on a loopback port."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
from support.fake_backend import DictBackend
from support.ports import free_port, silent_port
from support.waiting import eventually

from gateway.app import Gateway
from gateway.backends import open_proxy
from gateway.config import loads_config
from gateway.proxies import GrpcProxy
from gateway.proxies.grpc_channels import ChannelKey, ChannelPool, channel_pool
from gateway.proxies.grpc_proxy import tls_files
from gateway.proxies.remote_types import MAX_NAMES_PER_GET
from services.kernel.errors import Code, PropertyError

FAST = {"timeout": 2.0, "connect_timeout": 1.0, "backoff_initial": 0.05, "backoff_max": 0.5}
#: Services the remote gateway serves (sim robots), each reached through a proxy of its own here.
SERVED = 20

REMOTE_CONFIG = "\n".join(
    f'[[services]]\nname = "scout{k}"\ntype = "sim-robot"\noptions = {{ start = [{k}.0, 0.0] }}\n'
    for k in range(SERVED)
)


@pytest.fixture
async def remote() -> AsyncIterator[Gateway]:
    async with Gateway(loads_config('[gateway]\nlisten = "127.0.0.1:0"\n' + REMOTE_CONFIG)) as gateway:
        yield gateway


def proxy(address: str, remote_name: str, local_name: str = "", **options: object) -> GrpcProxy:
    opened = open_proxy(local_name or remote_name, f"grpc://{address}/{remote_name}", {**FAST, **options})
    assert isinstance(opened, GrpcProxy)
    return opened


async def test_proxies_to_one_gateway_share_one_channel_closed_with_the_last(remote: Gateway) -> None:
    pool = channel_pool()
    proxies = [proxy(remote.address, f"scout{k}") for k in range(SERVED)]
    for each in proxies:
        await each.start()
    assert (len(pool), pool.users) == (1, SERVED)
    (shared,) = pool.channels()
    for k, each in enumerate(proxies):
        assert (await each.get("location")).startswith(f"({k}")
    for each in proxies[:-1]:
        await each.aclose()
        await each.aclose()  # a proxy lets its channel go once
    assert (len(pool), pool.users, shared.closed) == (1, 1, False)
    assert await proxies[-1].get("properties")
    await proxies[-1].aclose()
    assert (len(pool), pool.users, shared.closed) == (0, 0, True)
    assert shared.channel.get_state() is grpc.ChannelConnectivity.SHUTDOWN
    # The next proxy to that gateway gets a new channel, not the closed one.
    again = proxy(remote.address, "scout0")
    await again.start()
    assert pool.channels()[0] is not shared
    assert await again.get("properties")
    await again.aclose()
    assert len(pool) == 0


async def test_other_settings_or_another_gateway_get_a_channel_of_their_own(remote: Gateway) -> None:
    pool = channel_pool()
    opened = [
        proxy(remote.address, "scout0"),
        proxy(remote.address, "scout1"),
        proxy(remote.address, "scout0", "slow0", timeout=4.0),
        proxy(f"127.0.0.1:{free_port()}", "scout0", "elsewhere"),
    ]
    for each in opened:
        await each.start()
    assert (len(pool), pool.users) == (3, 4)
    for each in opened:
        await each.aclose()
    assert len(pool) == 0


def test_tls_files_with_the_same_contents_make_the_same_channel_key(tmp_path: Path) -> None:
    first, copy, other = tmp_path / "ca.pem", tmp_path / "copy.pem", tmp_path / "other.pem"
    first.write_bytes(b"-----BEGIN CERTIFICATE-----\nA\n")
    copy.write_bytes(first.read_bytes())
    other.write_bytes(b"-----BEGIN CERTIFICATE-----\nB\n")
    url = "grpcs://127.0.0.1:5000/scout1"
    assert tls_files(url, {"ca": str(first)}) == tls_files(url, {"ca": str(copy)})
    assert tls_files(url, {"ca": str(first)}) != tls_files(url, {"ca": str(other)})
    assert tls_files("grpc://127.0.0.1:5000/scout1", {}) is None


async def test_a_channel_is_released_once_per_acquire(remote: Gateway) -> None:
    pool = ChannelPool()
    key = ChannelKey(remote.address, None, (), 1.0)
    first, second = pool.acquire(key), pool.acquire(key)
    assert first is second and first.users == 2
    await pool.release(first)
    assert not first.closed
    await pool.release(first)
    assert first.closed and len(pool) == 0
    with pytest.raises(RuntimeError, match="released more often than acquired"):
        await pool.release(first)


async def test_the_types_of_many_services_come_in_one_query(remote: Gateway) -> None:
    pool = channel_pool()
    proxies = [proxy(remote.address, f"scout{k}") for k in range(SERVED)]
    tasks_before = len(asyncio.all_tasks())
    for each in proxies:
        await each.start()
    # Starting proxies starts no task of their own: one query is on its way for all of them.
    assert len(asyncio.all_tasks()) - tasks_before <= 1
    await asyncio.gather(*(each.wait_connected(5.0) for each in proxies))
    assert {each.info.type for each in proxies} == {"mobile_robot"}
    (shared,) = pool.channels()
    assert shared.types.queries == 1
    for each in proxies:
        await each.aclose()


async def test_a_name_the_remote_registry_does_not_know_yet_leaves_the_others_their_answer(
    remote: Gateway,
) -> None:
    proxies = [proxy(remote.address, f"scout{k}") for k in range(SERVED)]
    early = proxy(remote.address, "late")  # not served there yet: its registry does not know it
    for each in [*proxies, early]:
        await each.start()
    await asyncio.gather(*(each.wait_connected(5.0) for each in proxies))
    assert {each.info.type for each in proxies} == {"mobile_robot"}
    (shared,) = channel_pool().channels()
    # The batch the unknown name failed was asked again in halves down to it (about log2 of the
    # batch), not once per service.
    assert shared.types.queries <= 1 + 2 * (SERVED + 1).bit_length(), shared.types.queries
    await early.wait_connected(5.0)
    assert early.info.type == "unknown"  # not "resource": asked again, it is known once served there
    remote.router.add("late", DictBackend({"temperature": "21.5"}, type="sensor"))

    async def asked_again() -> str:
        await early.wait_connected(5.0)
        return early.info.type

    assert await eventually(asked_again, lambda kind: kind == "sensor") == "sensor"
    for each in [*proxies, early]:
        await each.aclose()


async def test_a_batch_is_never_larger_than_its_bound(remote: Gateway) -> None:
    many = MAX_NAMES_PER_GET + 10
    proxies = [proxy(remote.address, f"scout{k % SERVED}", f"alias{k}") for k in range(many)]
    for each in proxies:
        await each.start()
    await asyncio.gather(*(each.wait_connected(5.0) for each in proxies))
    assert {each.info.type for each in proxies} == {"mobile_robot"}
    (shared,) = channel_pool().channels()
    # Twenty distinct names (aliases of one remote service share its question): one Get.
    assert shared.types.queries <= 2
    for each in proxies:
        await each.aclose()


async def test_a_dead_gateways_channel_waits_once_and_closes_when_unused() -> None:
    pool = channel_pool()
    async with Gateway(loads_config('[gateway]\nlisten = "127.0.0.1:0"\n' + REMOTE_CONFIG)) as remote:
        address = remote.address
        proxies = [proxy(address, f"scout{k}") for k in range(SERVED)]
        for each in proxies:
            await each.wait_connected(5.0)
        assert {each.info.type for each in proxies} == {"mobile_robot"}
    # The gateway is gone: every proxy on the shared channel says so, and waiting for it is one
    # watch of the channel, however many wait.
    for each in proxies:
        with pytest.raises(PropertyError) as gone:
            await each.get("location")
        assert gone.value.code in (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED), gone.value
    tasks_before = len(asyncio.all_tasks())
    waits = [asyncio.ensure_future(each.wait_connected(0.5)) for each in proxies]
    await asyncio.sleep(0.1)
    assert len(asyncio.all_tasks()) - tasks_before <= len(waits) + 1  # the waiters and one watch
    for wait in waits:
        with pytest.raises(PropertyError) as unreachable:
            await wait
        assert unreachable.value.code is Code.UNAVAILABLE
    (shared,) = pool.channels()
    for each in proxies:
        await each.aclose()
    assert len(pool) == 0 and shared.closed


async def test_closing_the_last_proxy_while_another_waits_for_the_type_ends_the_wait() -> None:
    async with silent_port() as port:
        silent = proxy(f"127.0.0.1:{port}", "scout0", timeout=30.0)
        await silent.start()
        (shared,) = channel_pool().channels()
        asked = shared.types.ask("scout1")
        await silent.aclose()  # the last user: the channel closes, the question with it
        with pytest.raises(PropertyError) as closed:
            await asyncio.wait_for(asked, 5.0)
        assert closed.value.code is Code.UNAVAILABLE
