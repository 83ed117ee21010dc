"""A cluster upgraded one gateway at a time, from the previous release's code to this one's.

The previous release is a git worktree of :data:`PREVIOUS_RELEASE` (the last commit before the
cluster protocol had versions), made in the test's temporary folder and removed at the end; its
gateways run its own code (``start_gateway(checkout=...)``). Three of them share a real etcd,
with two devices registered; each in turn is stopped (SIGTERM: it hands its devices over) and
started again from this tree under the same id, and after each step every gateway, old and new,
answers Gets and Sets on every device, forwarded both ways between the releases, and a Listen
through the gateway upgraded last goes on through the others' restarts. Without git,
the commit or etcd the tests skip, saying so.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from line_device_support import tcp_device
from support.cluster import cluster_config, stored
from support.etcd import EtcdServer
from support.gateway_process import ROOT, GatewayProcess, start_gateway
from support.ports import stable_ports
from support.waiting import eventually

from clients import AsyncClient
from clients.aio import Event
from clients.errors import PropertyServiceError
from gateway.cluster.records import GatewayRecord
from gateway.peer_protocol import SPOKEN, UNVERSIONED
from gateway.stores.address import parse_store_url
from gateway.stores.etcd import EtcdStore
from services.apps.registry.store import Kind

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

#: The previous release: the last commit whose gateways wrote no cluster protocol version.
PREVIOUS_RELEASE = "3d14d8f"
LEASE = 2.0
IDS = ("gw-a", "gw-b", "gw-c")


@pytest.fixture(scope="module")
def previous_release(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A worktree of the previous release, removed (and pruned from the repository) at the end."""
    git = shutil.which("git")
    if git is None:
        pytest.skip("git is not installed: the previous release cannot be checked out")
    known = subprocess.run(
        [git, "-C", str(ROOT), "cat-file", "-e", f"{PREVIOUS_RELEASE}^{{commit}}"],
        capture_output=True,
        check=False,
    )
    if known.returncode != 0:
        pytest.skip(f"commit {PREVIOUS_RELEASE} (the previous release) is not in this repository's history")
    folder = tmp_path_factory.mktemp("releases") / "prev-release"
    subprocess.run(
        [git, "-C", str(ROOT), "worktree", "add", "--detach", str(folder), PREVIOUS_RELEASE],
        capture_output=True,
        check=True,
    )
    try:
        yield folder
    finally:
        subprocess.run([git, "-C", str(ROOT), "worktree", "remove", "--force", str(folder)], check=False)
        subprocess.run([git, "-C", str(ROOT), "worktree", "prune"], check=False)


def _config(etcd: EtcdServer, gateway: str, line: str) -> str:
    return cluster_config(etcd, gateway, lease=LEASE, line=line)


async def _gateway_keys(etcd: EtcdServer) -> dict[str, dict[str, object]]:
    """Every ``gateways/ID`` key, as JSON, read through the gateway's own etcd store."""
    return {gid: json.loads(text) for gid, text in (await stored(etcd, Kind.GATEWAY)).items()}


async def _answers(address: str, device: str, rate: str) -> None:
    """A Set through the gateway at ``address`` reaches ``device`` and a Get reads it back."""
    async with AsyncClient(address, timeout=5.0) as client:
        assert await client.set(device, "rate_hz", rate) == rate
        assert await client.get(device, "rate_hz") == rate


async def test_a_cluster_of_the_previous_release_is_upgraded_one_gateway_at_a_time(
    previous_release: Path, etcd_server: Callable[..., EtcdServer], tmp_path: Path
) -> None:
    etcd = etcd_server()
    lines = {gid: f"127.0.0.1:{port}" for gid, port in zip(IDS, stable_ports(len(IDS)), strict=True)}
    gateways: dict[str, GatewayProcess] = {}
    release = dict.fromkeys(IDS, "previous")
    try:
        for gid in IDS:
            gateways[gid] = start_gateway(tmp_path, _config(etcd, gid, lines[gid]), checkout=previous_release)
        with (
            tcp_device("--service", "sim-sensor", "--name", "thermo") as thermo,
            tcp_device("--service", "sim-sensor", "--name", "hygro") as hygro,
        ):
            async with AsyncClient(gateways["gw-a"].address) as first:
                await first.set("registry", "services.thermo", "tcp://{}:{}".format(*thermo))
            async with AsyncClient(gateways["gw-c"].address) as last:
                await last.set("registry", "services.hygro", "tcp://{}:{}".format(*hygro))
            keys = await _gateway_keys(etcd)
            assert all("protocols" not in key for key in keys.values()), keys
            # A Listen through the gateway upgraded last stays open while the others restart.
            watcher = AsyncClient(gateways["gw-c"].address)
            seen: list[Event] = []

            async def follow() -> None:
                async for event in watcher.listen("thermo", "rate_hz"):
                    seen.append(event)

            following = asyncio.get_running_loop().create_task(follow())

            for step, upgraded in enumerate(IDS, start=1):
                if upgraded == "gw-c":  # its own restart ends the stream: check what it saw first
                    await eventually(
                        lambda: asyncio.sleep(0, seen[-1].value if seen else None),
                        lambda last: last == "2.3",
                        what="the last Set of step 2 on the Listen through gw-c",
                    )
                    assert not following.done(), following
                    assert not any(event.removed for event in seen), seen
                    assert sum(event.gap for event in seen) <= 2, "one gap at most per move of thermo"
                    following.cancel()
                    await asyncio.gather(following, return_exceptions=True)
                    await watcher.close()
                assert gateways[upgraded].stop() == 0, gateways[upgraded].output[-2000:]
                gateways[upgraded] = start_gateway(tmp_path, _config(etcd, upgraded, lines[upgraded]))
                release[upgraded] = "this"
                keys = await eventually(
                    lambda: _gateway_keys(etcd), lambda keys: set(keys) == set(IDS), what="three gateways"
                )
                for gid, key in keys.items():
                    spoken = sorted(SPOKEN if release[gid] == "this" else UNVERSIONED)
                    assert key.get("protocols", sorted(UNVERSIONED)) == spoken, (gid, key)
                # Every gateway, of either release, answers for both devices, whoever owns them now.
                for gid in IDS:
                    for device in ("thermo", "hygro"):
                        rate = f"{step}.{IDS.index(gid) + 1}"
                        await eventually(
                            lambda a=gateways[gid].address, d=device, r=rate: _answers(a, d, r),
                            retry_on=(PropertyServiceError,),
                            what=f"{device} through {gid} ({release[gid]} release) at step {step}",
                        )
            # Every gateway is of this release now, and forwards with the versions it speaks.
            keys = await _gateway_keys(etcd)
            assert {gid: key["protocols"] for gid, key in keys.items()} == dict.fromkeys(IDS, sorted(SPOKEN))
    finally:
        for gw in gateways.values():
            gw.stop()


async def test_a_gateway_refuses_to_join_a_cluster_whose_gateways_speak_no_protocol_it_speaks(
    etcd_server: Callable[..., EtcdServer], tmp_path: Path
) -> None:
    etcd = etcd_server()
    future = EtcdStore(parse_store_url(etcd.url), gateway_id="gw-future", lease=30.0)
    await future.start()
    try:
        record = GatewayRecord("127.0.0.1:1", protocols=frozenset({max(SPOKEN) + 1}))
        await future.put(Kind.GATEWAY, "gw-future", record.to_json(), leased=True)
        (line,) = stable_ports(1)
        refused = GatewayProcess(
            [
                *(sys.executable, "-m", "gateway.cli", "serve", "--listen", "127.0.0.1:0"),
                *("--config", str(_written(tmp_path, _config(etcd, "gw-here", f"127.0.0.1:{line}")))),
            ]
        )
        assert refused.proc.wait(30) == 1, refused.output[-2000:]
        refused.stop()
        assert "cannot join the cluster at" in refused.output, refused.output[-2000:]
        assert f"gw-future speaks {max(SPOKEN) + 1}" in refused.output
        assert set(await _gateway_keys(etcd)) == {"gw-future"}, "the refused gateway left its key"
    finally:
        await future.aclose()


def _written(folder: Path, config: str) -> Path:
    path = folder / "refused.toml"
    path.write_text(config)
    return path
