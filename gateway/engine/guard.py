"""The one access check every front end passes: identity, rules, scopes and the audit trail together.

The call layer (:mod:`gateway.engine.calls`: Get, Set, Describe), the listen
streams (:mod:`gateway.engine.listen`) and the line listener
(:mod:`gateway.fronts.line.listener`) hold one :class:`Guard` and ask it before they
touch a backend. What a request does is an :class:`~gateway.engine.rules.Operation`:

* Get (values and queries), Listen and Describe read (Describe asks about the
  service itself: the empty path, which only a ``**`` rule path matches);
* a Set on the registry of ``services.NAME`` registers (a URL) or unregisters
  (nothing); ``acquire``, ``renew`` and ``release`` (licences) and ``request`` (the
  scheduler, which licenses what it chooses to the caller) invoke; any
  other Set on the registry is ``admin``;
* any other Set writes a value or invokes an action. Only when the rules tell
  the two apart for this subject and path does the guard read the service's
  model to know which; otherwise the Set is ``write``.

With no rules, no ``[auth]`` and no token scopes, every check passes at the
cost of one attribute read (:attr:`Guard.checks`); Sets are still audited.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterable, Mapping, Sequence
from typing import Any

from gateway.audit import Audit, AuditSection
from gateway.config import Config
from gateway.engine.identity import ANONYMOUS, Authenticator, AuthSection
from gateway.engine.rules import Decision, Operation, Rules, Subject, refusal
from services.kernel.directory import CALLER
from services.kernel.errors import PropertyError
from services.kernel.model import Access, ServiceModel
from services.kernel.values import Value

#: The service whose ``services.NAME`` Sets register and unregister (gateway.config.REGISTRY_NAME).
REGISTRY = "registry"
_SERVICES_PREFIX = "services."
#: The registry's actions of consumers — licences, and the scheduler's ``request``, which licenses
#: what it chooses to the caller: invoked by any consumer that the rules let invoke them, not an
#: administration of the registry.
LICENCE_ACTIONS = frozenset({"acquire", "renew", "release", "request"})


#: How a subject that a service's configuration names (a chart's ``run_as``) proved who it is.
CONFIGURED = "config"


def subject_of(caller: object) -> Subject:
    """The subject a :data:`services.kernel.directory.CALLER` stands for: a Subject as the call layer set
    it, or the name a service's configuration gives (trusted as the config is); anyone else
    (None included) is anonymous."""
    if isinstance(caller, Subject):
        return caller
    if isinstance(caller, str) and caller:
        return Subject(caller, authenticated=True, via=CONFIGURED)
    return ANONYMOUS


def current_subject() -> Subject:
    """The subject of the call being carried out, for checks made deep inside a service (the
    registry's admin check, the holder of a licence): set by the call layer when a call starts
    (:data:`services.kernel.directory.CALLER`), copied into any task the call goes on in; anonymous
    when none is."""
    return subject_of(CALLER.get())


def registry_operation(path: str, value: Value) -> Operation:
    """What a Set of ``path`` to ``value`` on the registry does."""
    if path.startswith(_SERVICES_PREFIX) and "." not in path[len(_SERVICES_PREFIX) :]:
        return Operation.REGISTER if value else Operation.UNREGISTER
    if path in LICENCE_ACTIONS:
        return Operation.INVOKE
    return Operation.ADMIN


class Guard:
    """Identity, rules and audit; see the module docstring."""

    def __init__(
        self,
        rules: Rules | None = None,
        auth: AuthSection | None = None,
        audit: AuditSection | None = None,
    ) -> None:
        """Reads the ``[auth]`` key files now; InvalidArgument naming the file when one cannot be used."""
        self.rules = rules or Rules()
        self.authenticator = Authenticator(auth or AuthSection())
        self.audit = Audit(audit or AuditSection())
        #: False when nothing is ever refused: no rules, and no tokens (whose scopes could narrow).
        self.checks = bool(self.rules) or self.authenticator.checks_tokens

    @classmethod
    def from_config(cls, config: Config) -> Guard:
        """The guard a config describes (its ``[auth]``, ``[[rules]]`` and ``[audit]``)."""
        return cls(Rules(config.rules), config.auth, config.audit)

    def identify_call(self, context: Any) -> Subject:
        """The subject of a gRPC call (``context``: a ``grpc.aio.ServicerContext``); Unauthenticated
        for a bad token, audited."""
        return self.identify(context.invocation_metadata(), context.auth_context())

    def identify(
        self, metadata: Iterable[tuple[str, str | bytes]] | None, auth_context: Mapping[str, Sequence[bytes]]
    ) -> Subject:
        """The subject of a request of any front end: its ``authorization`` metadata (or header) and
        its certificate as grpc's ``auth_context()`` names it; Unauthenticated for a bad token, audited."""
        try:
            return self.authenticator.identify(metadata, auth_context)
        except PropertyError as exc:
            self.audit.record(ANONYMOUS, "", "", Operation.READ, exc)
            raise

    def may(self, subject: Subject, service: str, path: str, operation: Operation) -> bool:
        """Whether the rules and scopes allow it (nothing logged: for skipping wildcard matches)."""
        return not self.checks or self.rules.check(subject, service, path, operation).allowed

    def require(self, subject: Subject, service: str, path: str, operation: Operation) -> None:
        """Raise UNAUTHENTICATED or PERMISSION_DENIED naming the rule unless it is allowed; audited."""
        if not self.checks:
            return
        self._enforce(subject, service, path, operation, self.rules.check(subject, service, path, operation))

    def _enforce(
        self, subject: Subject, service: str, path: str, operation: Operation, decision: Decision
    ) -> None:
        if not decision.allowed:
            err = refusal(subject, service, path, operation, decision)
            self.audit.record(subject, service, path, operation, err)
            raise err

    def refused_read(
        self, subject: Subject, reads: Iterable[tuple[str, str]], *, audit: bool
    ) -> PropertyError | None:
        """The refusal of the first of ``reads`` ((service, path) pairs) that ``subject`` may not
        read, recorded when ``audit``; None when every one may be read."""
        if not self.checks:
            return None
        for service, path in reads:
            decision = self.rules.check(subject, service, path, Operation.READ)
            if not decision.allowed:
                err = refusal(subject, service, path, Operation.READ, decision)
                if audit:
                    self.audit.record(subject, service, path, Operation.READ, err)
                return err
        return None

    def reader(self, subject: Subject) -> Callable[[str, str], bool] | None:
        """``(service, path) → may subject read it``, or None when everything may be read."""
        if not self.checks:
            return None
        return lambda service, path: self.may(subject, service, path, Operation.READ)

    def set_operation(self, subject: Subject, service: str, path: str, value: Value) -> Operation | None:
        """The Set's operation, checked (raises when refused); None when only the model can tell."""
        if service == REGISTRY:
            operation = registry_operation(path, value)
        elif not self.checks:
            operation = Operation.WRITE
        else:
            rules = self.rules
            write = rules.check(subject, service, path, Operation.WRITE)
            invoke = rules.check(subject, service, path, Operation.INVOKE)
            if write.allowed != invoke.allowed:
                return None
            # Decided already: the same for a write and an action.
            self._enforce(subject, service, path, Operation.WRITE, write)
            return Operation.WRITE
        self.require(subject, service, path, operation)
        return operation

    async def set_operation_from_model(
        self, subject: Subject, service: str, path: str, describe: Awaitable[ServiceModel]
    ) -> Operation:
        """The operation of a Set the rules treat differently as a write and as an action, checked."""
        model = await describe
        access = next((p.access for p in model.properties if p.name == path), Access.UNKNOWN)
        operation = Operation.INVOKE if access is Access.ACTION else Operation.WRITE
        self.require(subject, service, path, operation)
        return operation

    def may_administer(self, name: str) -> bool:
        """Whether the caller of the current Set may unregister or replace the configured service ``name``.

        Only a rule can make someone admin: with no rules, configured services stay as configured.
        """
        return self.checks and self.may(current_subject(), REGISTRY, f"services.{name}", Operation.ADMIN)

    def audited(
        self, subject: Subject, service: str, path: str, operation: Operation, error: BaseException | None
    ) -> None:
        """Record a Set's outcome (``error`` None: it succeeded)."""
        self.audit.record(subject, service, path, operation, error)
