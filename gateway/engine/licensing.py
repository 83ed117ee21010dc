"""Who holds a licence, and the check of every Set against the licences held.

The registry's :class:`~services.apps.registry.Licences` knows licences by holder
name; this module says which name a caller holds them under:

* a caller with a proven identity (a client certificate or a token,
  :mod:`gateway.engine.identity`) holds them under its name, on any connection and any
  front end;
* an anonymous caller holds them under its Session (``session-<token>``):
  only requests on the same Session stream are its own, and the licences end
  with the Session;
* an anonymous unary call (or HTTP request) cannot hold a licence: nothing
  ties its next request to it. Acquiring one is FAILED_PRECONDITION saying so.

Whichever the holder, a licence acquired on a Session ends with that Session
(a holder that vanishes loses it).

**Who may lock what.** A licence keeps everyone else from changing what it
covers, so acquiring one needs the right to change it: ``write`` by the rules on
the subtree it locks (its path; for a whole service the service itself, which
only a ``**`` rule path matches), checked as the caller (:func:`may_license`).
A subject allowed only to invoke ``registry/acquire`` can lock nothing. The
scheduler's ``request`` licenses whole providers to its caller, so it picks only
those the caller may ``write`` (:func:`may_provide`).
"""

from __future__ import annotations

from collections.abc import Callable

from gateway.engine.guard import REGISTRY, Guard, current_subject
from gateway.engine.rules import Operation, Subject
from services.apps.registry import SESSION_HOLDER_PREFIX, Caller, LicenceCheck, Licences, ProviderCheck
from services.kernel.errors import FailedPrecondition

__all__ = [
    "SESSION_HOLDER_PREFIX",
    "caller_of",
    "check_set",
    "current_caller",
    "holder_of",
    "may_license",
    "may_provide",
]


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


def may_license(guard: Guard) -> LicenceCheck:
    """The registry's check of an ``acquire``: the caller of the Set may ``write`` the subtree it locks
    (UNAUTHENTICATED or PERMISSION_DENIED naming the rule otherwise; audited)."""

    def check(service: str, subtree: str) -> None:
        guard.require(current_subject(), service, subtree, Operation.WRITE)

    return check


def may_provide(guard: Guard) -> ProviderCheck:
    """The scheduler's test of the providers it may license to the caller of the Set: those it
    may ``write`` whole by the rules (asked quietly: a refused provider is simply not picked)."""

    def for_caller() -> Callable[[str], bool] | None:
        if not guard.checks:
            return None
        subject = current_subject()
        return lambda service: guard.may(subject, service, "", Operation.WRITE)

    return for_caller
