"""Gateways that form one cluster on a real etcd, as the cluster tests start them.

``cluster_config(etcd, "gw-a", lease=2.0)`` is the config of one member (``[registry]`` on the
etcd, its own ``gateway_id``); ``running_gateways(folder, configs)`` starts one real gateway
process a config and stops them all when the block ends, waking any a test froze first;
``running_cluster`` does both for gateways that take tokens and devices on a line listener of
their own; ``stored(etcd, Kind.OWNER)`` reads one kind of the cluster's keys as a gateway reads them::

    with running_gateways(tmp_path, {gid: cluster_config(etcd, gid, lease=2.0) for gid in IDS}) as gws:
        ...
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from gateway.stores.address import parse_store_url
from gateway.stores.etcd import EtcdStore
from services.apps.registry.store import Kind
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess, start_gateway
from support.ports import stable_ports


def cluster_config(
    etcd: EtcdServer,
    gateway: str,
    *,
    lease: float,
    quick_checks: bool = True,
    line: str | None = None,
    secret_file: str | None = None,
    registry: str = "",
) -> str:
    """The config of cluster member ``gateway`` on ``etcd`` with a ``lease``-second store lease.

    ``quick_checks``: the registry checks its devices every 0.5 s with a 1 s timeout, so that a test
    sees a failure soon; ``line``: the line protocol's listen address; ``secret_file``: the JWT
    secret's file; ``registry``: more ``[registry]`` keys, one a line."""
    sections = []
    if line is not None:
        sections.append(f'[gateway]\nline_listen = "{line}"\n')
    if secret_file is not None:
        sections.append(f'[auth]\njwt_secret_file = "{secret_file}"\n')
    keys = [f'store = "{etcd.url}"', f"store_lease = {lease}", f'gateway_id = "{gateway}"']
    if quick_checks:
        keys += ["period = 0.5", "timeout = 1.0"]
    keys += [key.strip() for key in registry.splitlines() if key.strip()]
    sections.append("[registry]\n" + "".join(f"{key}\n" for key in keys))
    return "\n".join(sections)


@contextlib.contextmanager
def running_gateways(folder: Path, configs: Mapping[str, str]) -> Iterator[dict[str, GatewayProcess]]:
    """One gateway process a config, started in order in ``folder``, by the same id; all stopped at
    the end (a frozen one is sent SIGCONT first, so that it can stop)."""
    gateways: dict[str, GatewayProcess] = {}
    try:
        for gateway, config in configs.items():
            gateways[gateway] = start_gateway(folder, config)
        yield gateways
    finally:
        for gw in gateways.values():
            if gw.proc.poll() is None:  # never signal a PID this process has reaped
                with contextlib.suppress(ProcessLookupError):
                    os.kill(gw.proc.pid, signal.SIGCONT)
            gw.stop()


@contextlib.contextmanager
def running_cluster(
    etcd: EtcdServer, folder: Path, ids: Sequence[str], *, lease: float, secret: str
) -> Iterator[tuple[dict[str, GatewayProcess], dict[str, str]]]:
    """Gateways ``ids`` on ``etcd``, each with its own line listener and ``secret`` as the HS256 key
    of the tokens it takes: (id → process, id → its line listener's address)."""
    (folder / "jwt.secret").write_text(secret)
    lines = {gateway: f"127.0.0.1:{port}" for gateway, port in zip(ids, stable_ports(len(ids)), strict=True)}
    configs = {
        gateway: cluster_config(etcd, gateway, lease=lease, line=lines[gateway], secret_file="jwt.secret")
        for gateway in ids
    }
    with running_gateways(folder, configs) as gateways:
        yield gateways, lines


async def stored(etcd: EtcdServer, kind: Kind) -> dict[str, str]:
    """The keys of ``kind`` in ``etcd`` now (name → value), read through the gateway's own store."""
    store = EtcdStore(parse_store_url(etcd.url), gateway_id="test-reader")
    await store.start()
    try:
        return await store.read(kind)
    finally:
        await store.aclose()
