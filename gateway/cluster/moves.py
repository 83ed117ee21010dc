"""Planned moves: which gateways take devices, and how many a gateway hands over to rebalance.

A device changes owner without a failure in two cases (docs/scale-out.md, "Operating a cluster"):

* **Drain.** An admin drains a gateway: it hands every device it owns over and takes nothing new.
  The devices go the way a dead gateway's do (:mod:`gateway.cluster.failover`), dealt to the
  least-loaded gateways that take devices (:func:`taking_loads`: every live gateway that is not
  draining), but the drained gateway is alive: it closes each device's connection only once the
  calls on it have ended, and every gateway holds the calls that arrive meanwhile until the new
  owner answers, instead of refusing them.
* **Rebalance.** A gateway that owns more than ``spread`` devices beyond the least-loaded one hands
  :func:`rebalance_quota` of them over, at most ``batch`` at a time, the same way; it looks again
  once they have moved. Each gateway decides only for itself, from the loads every gateway sees,
  so that together they never hand over more than would even the loads out.

Nothing here touches the network or the store.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["rebalance_quota", "taking_loads"]


def taking_loads(loads: Mapping[str, int], draining: set[str]) -> dict[str, int]:
    """The loads of the gateways that take devices: every live one that is not draining. When every
    gateway is draining, all of them (a device is better owned by a draining gateway than by none)."""
    taking = {gateway: load for gateway, load in loads.items() if gateway not in draining}
    return taking or dict(loads)


def rebalance_quota(loads: Mapping[str, int], me: str, *, movable: int, spread: int, batch: int) -> int:
    """How many devices ``me`` hands over now to even the loads out (0: none).

    ``loads``: the devices each gateway that takes devices owns, ``me`` among them; ``movable``:
    those of ``me``'s that can move (a device that dialled in cannot: nobody else can dial it).
    ``me`` hands over when it owns more than ``spread`` beyond the least-loaded other gateway: what
    it owns beyond the mean (rounded down) and at most half the difference, so that the gateways
    handing over at once never push the lightest past the mean; at most ``batch``.
    """
    if me not in loads or len(loads) < 2 or spread < 0 or batch < 1:
        return 0
    mine = loads[me]
    lightest = min(load for gateway, load in loads.items() if gateway != me)
    if mine - lightest <= spread:
        return 0
    beyond_mean = mine - sum(loads.values()) // len(loads)
    return max(0, min(batch, movable, beyond_mean, (mine - lightest) // 2))
