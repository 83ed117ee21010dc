"""``psctl cluster``: the gateways of a cluster, who owns what, and the admin's drain and rebalance.

Everything comes from the registry of the gateway called (docs/scale-out.md, "Operating a
cluster"): ``cluster`` (JSON of every member: address, version, lease, health, devices owned,
load, read-only state, drain), ``services.*.owner`` and ``services.*.owner_since`` per device, and
the actions ``cluster.drain``, ``cluster.undrain`` and ``cluster.rebalance`` (an admin's, by the rules).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from datetime import datetime
from typing import Any

from clients.aio import AsyncClient
from clients.errors import NotFound

__all__ = ["ACTIONS", "cluster_command", "device_rows", "member_rows"]

#: What ``psctl cluster ACTION`` may name, and whether it takes a gateway id.
ACTIONS = {"show": False, "drain": True, "undrain": True, "rebalance": False}


def member_rows(view: dict[str, Any], now: float) -> list[list[str]]:
    """The members' table (a header first): one row per gateway of the cluster view ``view``."""
    rows = [["GATEWAY", "ADDRESS", "VERSION", "HEALTH", "STATE", "OWNED", "CALLS/S", "LISTENS", "LEASE"]]
    for member in view.get("members", []):
        if member.get("draining"):
            state = "draining"
        elif member.get("read_only"):
            state = "read-only"
        else:
            state = "serving"
        expires = float(member.get("lease_expires") or 0.0)
        lease = f"{expires - now:+.1f}s" if expires else "-"
        rows.append(
            [
                str(member.get("id", "?")),
                str(member.get("address", "")),
                str(member.get("version") or "-"),
                str(member.get("health", "?")),
                state,
                str(member.get("owned", 0)),
                f"{float(member.get('calls_per_s') or 0.0):g}",
                str(member.get("listens", 0)),
                lease,
            ]
        )
    return rows


def device_rows(owners: dict[str, str], since: dict[str, str]) -> list[list[str]]:
    """The devices' table (a header first): name, owner, and since when (this gateway's clock); the
    gateway's own services (no owner: they are not the cluster's) are left out."""
    rows = [["DEVICE", "OWNER", "SINCE"]]
    for name in sorted(name for name, owner in owners.items() if owner):
        stamp = float(since.get(name) or 0.0)
        when = datetime.fromtimestamp(stamp).strftime("%H:%M:%S") if stamp else "-"
        rows.append([name, owners[name] or "-", when])
    return rows


def _by_service(found: dict[str, Any], leaf: str) -> dict[str, str]:
    """``services.NAME.LEAF = value`` matches → NAME → value."""
    out: dict[str, str] = {}
    for path, value in found.items():
        head, _, rest = path.partition(".")
        name, _, tail = rest.rpartition(".")
        if head == "services" and tail == leaf and name:
            out[name] = value if isinstance(value, str) else ""
    return out


async def _read_view(client: AsyncClient) -> dict[str, Any]:
    try:
        text = await client.get("registry", "cluster")
    except NotFound:
        raise NotFound(
            None,
            "this gateway is not in a cluster: its registry has no 'cluster' (a cluster's gateways "
            'share [registry] store = "etcd://...")',
        ) from None
    return json.loads(text) if isinstance(text, str) and text else {}


async def cluster_command(
    client: AsyncClient,
    action: str,
    gateway: str | None,
    *,
    devices: bool,
    watch: bool,
    count: int | None,
    as_json: bool,
    table: Callable[[list[list[str]]], None],
    out: Callable[[str], None],
) -> None:
    """Run ``psctl cluster``: show the view (once, or each time it changes with ``watch``), or carry
    an admin action out and show the view after it."""
    if action != "show":
        path = f"cluster.{action}"
        answer = await client.set("registry", path, gateway or "")
        if as_json:
            out(json.dumps({"action": action, "gateway": gateway, "answer": answer}))
        else:
            out(str(answer))
        return
    if watch:
        shown = 0
        async for event in client.listen("registry", "cluster"):
            if event.removed or not isinstance(event.value, str) or not event.value:
                continue
            await _show(
                client, json.loads(event.value), devices=devices, as_json=as_json, table=table, out=out
            )
            shown += 1
            if count is not None and shown >= count:
                return
        return
    await _show(client, await _read_view(client), devices=devices, as_json=as_json, table=table, out=out)


async def _show(
    client: AsyncClient,
    view: dict[str, Any],
    *,
    devices: bool,
    as_json: bool,
    table: Callable[[list[list[str]]], None],
    out: Callable[[str], None],
) -> None:
    owners: dict[str, str] = {}
    since: dict[str, str] = {}
    if devices:
        owners = _by_service(await client.get_matching("registry", "services.*.owner"), "owner")
        since = _by_service(await client.get_matching("registry", "services.*.owner_since"), "owner_since")
    if as_json:
        shown = dict(view)
        if devices:
            shown["devices"] = {
                name: {"owner": owner, "since": float(since.get(name) or 0.0)}
                for name, owner in sorted(owners.items())
                if owner
            }
        out(json.dumps(shown, sort_keys=True))
        return
    policy = view.get("rebalance") or {}
    out(
        f"cluster seen by {view.get('gateway', '?')} on {view.get('store', '?')}: "
        f"{view.get('services', 0)} services, {view.get('unowned', 0)} without an owner; rebalance "
        f"{'by policy' if policy.get('policy') else 'when asked'} "
        f"(spread {policy.get('spread', '?')}, batch {policy.get('batch', '?')})"
    )
    table(member_rows(view, time.time()))
    for gateway, order in sorted((view.get("drains") or {}).items()):
        at = datetime.fromtimestamp(float(order.get("at") or 0.0)).strftime("%H:%M:%S")
        out(f"{gateway} drained by {order.get('by') or '?'} at {at}")
    if devices:
        table(device_rows(owners, since))
