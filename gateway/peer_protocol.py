"""The cluster protocol: the version of what gateways say to each other, apart from the package's.

Gateways of a cluster speak to each other twice: through the keys they write in the shared store
(docs/scale-out.md, "How it works") and through the calls one makes to another (a forwarded Get,
Set or Listen, a question about a service's type). Both change now and then: a key gains a field
whose meaning the others must know, a call gains metadata the owner must honour. Each such change
is a new **cluster protocol version**, an integer counted apart from the package's version, and a
gateway speaks a set of them: its own and the ones before that it still understands.

* A gateway's ``gateways/ID`` key names the versions it speaks (``"protocols": [1, 2]``), and so
  does every call it makes to another gateway (the ``ps-protocols`` metadata, ``1,2``).
* A key or a call that names none comes from a gateway of version 1, the first cluster (which
  wrote no version): :data:`UNVERSIONED`.
* Two gateways can run together when they share a version (:func:`common`). A gateway refuses to
  join a cluster with a live gateway it shares none with (:func:`check_cluster`), and answers a
  call from one FAILED_PRECONDITION (:func:`check_caller`), each naming both sets: the operator
  learns which gateway to upgrade.

Version 2 (this release) added the versions themselves; its keys and calls are otherwise those of
version 1, so it speaks both and runs beside a gateway of the previous release during a rolling
upgrade. A release that changes a key's meaning adds a version, and drops the oldest one only when
no release that speaks nothing newer may still be running (docs/scale-out.md, "Versions").
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from services.kernel.errors import FailedPrecondition

__all__ = [
    "CLUSTER_PROTOCOL",
    "PROTOCOLS_KEY",
    "SPOKEN",
    "SPOKEN_HEADER",
    "UNVERSIONED",
    "ProtocolMismatch",
    "check_caller",
    "check_cluster",
    "common",
    "format_protocols",
    "parse_protocols",
    "read_protocols",
]

#: The cluster protocol this gateway writes and calls with: the newest it speaks.
CLUSTER_PROTOCOL = 2
#: Every version this gateway understands, in keys and in calls.
SPOKEN: frozenset[int] = frozenset({1, 2})
#: What a key or a call without versions speaks: the first cluster's protocol.
UNVERSIONED: frozenset[int] = frozenset({1})
#: The metadata key of the versions a gateway-to-gateway call speaks (comma-separated integers).
PROTOCOLS_KEY = "ps-protocols"
#: The metadata every call to another gateway carries: the versions this one speaks.
SPOKEN_HEADER: tuple[str, str] = (PROTOCOLS_KEY, ",".join(str(v) for v in sorted(SPOKEN)))
#: Versions one key or call may name; more is not a gateway of this project.
_MAX_NAMED = 32


class ProtocolMismatch(FailedPrecondition):
    """Two gateways share no cluster protocol version: they cannot run in one cluster."""


def format_protocols(spoken: Iterable[int]) -> str:
    """The versions as the ``ps-protocols`` metadata carries them: ``1,2``."""
    return ",".join(str(version) for version in sorted(spoken))


def parse_protocols(text: str | bytes) -> frozenset[int] | None:
    """The versions a ``ps-protocols`` value names; None when it is not a list of positive integers."""
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    parts = text.split(",")
    if len(parts) > _MAX_NAMED or not all(part.strip().isdigit() for part in parts):
        return None
    versions = frozenset(int(part) for part in parts)
    return versions if versions and 0 not in versions else None


def read_protocols(value: object) -> frozenset[int] | None:
    """The versions a ``gateways/ID`` key's ``protocols`` field names (absent: :data:`UNVERSIONED`);
    None when the field is there but not a list of positive integers."""
    if value is None:
        return UNVERSIONED
    if not isinstance(value, list) or not value or len(value) > _MAX_NAMED:
        return None
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value):
        return None
    return frozenset(value)


def common(ours: Iterable[int], theirs: Iterable[int]) -> frozenset[int]:
    """The versions two gateways both speak (empty: they cannot run together)."""
    return frozenset(ours) & frozenset(theirs)


def _shown(versions: Iterable[int]) -> str:
    return ", ".join(str(v) for v in sorted(versions))


def check_cluster(gateways: Mapping[str, frozenset[int]], *, me: str, store: str) -> None:
    """Refuse to join a cluster (:class:`ProtocolMismatch`) when a live gateway of it, other than
    ``me``, shares no version with this one; ``gateways``: id → the versions its key names."""
    strangers = {
        gid: spoken for gid, spoken in sorted(gateways.items()) if gid != me and not common(SPOKEN, spoken)
    }
    if not strangers:
        return
    named = "; ".join(f"{gid} speaks {_shown(spoken)}" for gid, spoken in strangers.items())
    raise ProtocolMismatch(
        f"cannot join the cluster at {store}: this gateway speaks cluster protocol {_shown(SPOKEN)} "
        f"and {named}; gateways of these releases cannot run together: upgrade one gateway at a "
        'time from the release before (docs/scale-out.md, "Versions")'
    )


def check_caller(text: str | bytes) -> None:
    """Refuse a call from a gateway (its ``ps-protocols`` metadata ``text``) that shares no
    version with this one (:class:`ProtocolMismatch`); a value that is not a list of versions too."""
    theirs = parse_protocols(text)
    if theirs is None:
        raise ProtocolMismatch(f"{PROTOCOLS_KEY}: not a list of cluster protocol versions: {text!r:.80}")
    if not common(SPOKEN, theirs):
        raise ProtocolMismatch(
            f"the calling gateway speaks cluster protocol {_shown(theirs)} and this one "
            f'{_shown(SPOKEN)}: they cannot run in one cluster (docs/scale-out.md, "Versions")'
        )
