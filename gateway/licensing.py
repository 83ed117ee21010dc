"""Who holds a licence, and the check of every Set against the licences held.

The registry's :class:`~services.registry.Licences` knows licences by holder
name; this module says which name a caller holds them under:

* a caller with a proven identity (a client certificate or a token,
  :mod:`gateway.identity`) holds them under its name, on any connection and any
  front end;
* an anonymous caller holds them under its Session (``session-<token>``):
  only requests on the same Session stream are its own, and the licences end
  with the Session;
* an anonymous unary call (or HTTP request) cannot hold a licence: nothing
  ties its next request to it. Acquiring one is FAILED_PRECONDITION saying so.

Whichever the holder, a licence acquired on a Session ends with that Session
(a holder that vanishes loses it).
"""

from __future__ import annotations

from gateway.guard import REGISTRY, current_subject
from gateway.rules import Subject
from services.errors import FailedPrecondition
from services.registry import SESSION_HOLDER_PREFIX, Caller, Licences

__all__ = ["SESSION_HOLDER_PREFIX", "caller_of", "check_set", "current_caller", "holder_of"]


def holder_of(subject: Subject) -> str:
    """The holder name requests of ``subject`` count as ("" for an anonymous unary caller)."""
    if subject.authenticated:
        return subject.name
    if subject.session:
        return SESSION_HOLDER_PREFIX + subject.session
    return ""


def caller_of(subject: Subject) -> Caller:
    """(holder, session) of ``subject`` acquiring a licence; FailedPrecondition when it cannot hold one."""
    holder = holder_of(subject)
    if not holder:
        raise FailedPrecondition(
            "an anonymous caller can hold a licence only on a Session (it ends with the Session): "
            "open a Session, or call with a client certificate or a token"
        )
    return holder, subject.session


def current_caller() -> Caller:
    """:func:`caller_of` the subject of the Set being carried out (the registry's caller source)."""
    return caller_of(current_subject())


def check_set(licences: Licences | None, subject: Subject, service: str, path: str) -> None:
    """FailedPrecondition, naming the holder and the expiry, when another holds ``service``/``path``.

    The registry's own properties are never licensed (its licence actions must stay open).
    """
    if licences is None or service == REGISTRY:
        return
    licences.check_set(service, path, holder_of(subject))
