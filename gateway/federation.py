"""Federation loops: a request that comes back to a gateway it already passed through is refused.

A ``grpc://`` service is another gateway's service. Registered carelessly (a
gateway naming itself, or two gateways naming each other's proxies) a Get would
travel round the loop until its deadline, every hop holding a call and memory.
Each gateway has an id; every call a gateway makes through its gRPC proxy
carries, in the ``ps-via`` metadata, the ids of the gateways the request has
passed through. A gateway that finds its own id there refuses the call with
INVALID_ARGUMENT naming the loop, and so does one that finds more than
:data:`MAX_HOPS` ids: the loop ends at its first turn, and at most
:data:`MAX_HOPS` gateways ever hold the request.
"""

from __future__ import annotations

import contextvars
import secrets

from gateway.logs import REQUEST_ID_HEADER, current_request_id
from gateway.peer_protocol import SPOKEN_HEADER
from services.kernel.errors import InvalidArgument

#: The metadata key of the chain of gateways (comma-separated ids, the first gateway first).
VIA_KEY = "ps-via"
#: Gateways one request may pass through; federation deeper than this is a mistake, not a design.
MAX_HOPS = 8

#: The gateways the request being served has passed through, this one last (empty: no request).
VIA: contextvars.ContextVar[tuple[str, ...]] = contextvars.ContextVar("via", default=())


def new_gateway_id() -> str:
    """A gateway's id for the ``ps-via`` chain: random, short, not a secret."""
    return secrets.token_hex(6)


def enter(via: str | bytes | None, own_id: str) -> None:
    """Start serving a call whose ``ps-via`` metadata is ``via`` (None: it has none): refuse a loop
    or too long a chain (INVALID_ARGUMENT), else note the chain."""
    if not via:
        VIA.set((own_id,))  # a call straight from a client: the commonest case
        return
    text = via.decode(errors="replace") if isinstance(via, bytes) else via
    chain = tuple(part for part in text.split(",")[: MAX_HOPS + 1] if part)
    if own_id in chain:
        shown = " → ".join((*chain, own_id))
        raise InvalidArgument(
            f"federation loop: the request came back to a gateway it passed through ({shown}); "
            "a grpc:// service must not lead back to a gateway on its way"
        )
    if len(chain) >= MAX_HOPS:
        raise InvalidArgument(f"federation too deep: the request passed through {len(chain)} gateways")
    VIA.set((*chain, own_id))


def outgoing() -> tuple[tuple[str, str], ...]:
    """The metadata a call to another gateway carries on behalf of the request being served:
    the cluster protocol versions this gateway speaks, the ``ps-via`` chain, and the request id,
    so the next gateway's log lines carry it too."""
    via = VIA.get()
    metadata = (SPOKEN_HEADER, (VIA_KEY, ",".join(via))) if via else (SPOKEN_HEADER,)
    request_id = current_request_id()
    return (*metadata, (REQUEST_ID_HEADER, request_id)) if request_id is not None else metadata
