"""Who may do what: ``[[rules]]`` — subject × service × property path × operation → permit or deny.

Pure: no I/O, no gRPC. The call layer, the listen streams and the line
listener ask :meth:`Rules.check` before they touch a backend (see
``docs/security.md``, "Rules").

**Path patterns.** A rule's ``path`` is dotted, like a property path; a
segment ``*`` matches exactly one segment, and a last segment ``**`` matches
any number of segments, none included: ``location.**`` matches ``location``,
``location.x`` and ``location.x.y``; ``**`` alone matches every path and the
service itself (the empty path a Describe asks about).

**Best match wins.** Among the rules that match a request (subject, service,
path and operation), the most specific decides; specificity is compared in
this order:

1. the service: a name beats ``*``;
2. the path: more literal segments; then a longer literal prefix (literal
   segments before the first wildcard); then a fixed depth (no ``**``) beats
   ``**``; then fewer ``*`` segments;
3. the subject: a name beats ``*``.

At the same specificity ``deny`` beats ``permit``. When no rule matches and
any rule is configured, the request is refused (implicit deny).

**Token scopes only narrow.** A bearer token that carries a ``scope`` claim
(``read:scout1 write:scout1.speed``) allows at most what its scopes name, and
never more than the rules allow (:class:`Scopes`).
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from services.kernel.errors import InvalidArgument, PermissionDenied, PropertyError, Unauthenticated
from services.kernel.paths import WILDCARD, validate_pattern, validate_service_name

#: The last segment of a rule's path that matches any number of segments (none included).
ANY_DEPTH = "**"
#: The subject of a caller that gave no credentials.
ANONYMOUS_NAME = "anonymous"
#: Decisions remembered per :class:`Rules` before the memory starts over (bounds its size).
_CACHE_SIZE = 4096


class Operation(enum.StrEnum):
    """What a request does, as rules and scopes name it."""

    #: Get (of a value or a query), Listen, Describe.
    READ = "read"
    #: Set of a value.
    WRITE = "write"
    #: Set of an action.
    INVOKE = "invoke"
    #: Set of ``services.NAME`` on the registry to a URL.
    REGISTER = "register"
    #: Set of ``services.NAME`` on the registry to nothing.
    UNREGISTER = "unregister"
    #: Any other Set on the registry, and replacing or removing what the config set up.
    ADMIN = "admin"


def parse_operation(text: str, where: str) -> Operation:
    """``text`` as an :class:`Operation`; InvalidArgument naming ``where`` otherwise."""
    try:
        return Operation(text)
    except ValueError:
        known = ", ".join(op.value for op in Operation)
        raise InvalidArgument(f"{where}: unknown operation {text!r} (known: {known})") from None


def check_rule_path(path: str, where: str) -> tuple[str, ...]:
    """The segments of a rule path pattern; InvalidArgument when it is not one."""
    segments = tuple(path.split("."))
    head = segments[:-1] if segments[-1] == ANY_DEPTH else segments
    if ANY_DEPTH in head:
        raise InvalidArgument(f"{where}: {ANY_DEPTH} may only be the last segment of {path!r}")
    if head:
        try:
            validate_pattern(".".join(head))
        except InvalidArgument as exc:
            raise InvalidArgument(f"{where}: {exc.message}") from None
    return segments


def path_matches(segments: tuple[str, ...], path: str) -> bool:
    """Whether the pattern ``segments`` (from :func:`check_rule_path`) matches ``path`` ("" = the service)."""
    parts = path.split(".") if path else []
    if segments and segments[-1] == ANY_DEPTH:
        fixed = segments[:-1]
        if len(parts) < len(fixed):
            return False
    else:
        fixed = segments
        if len(parts) != len(fixed):
            return False
    return all(want in (WILDCARD, part) for want, part in zip(fixed, parts, strict=False))


def path_specificity(segments: tuple[str, ...]) -> tuple[int, int, int, int]:
    """Larger is more specific: (literal segments, literal prefix, fixed depth, -``*`` segments)."""
    literals = sum(1 for s in segments if s not in (WILDCARD, ANY_DEPTH))
    prefix = 0
    for s in segments:
        if s in (WILDCARD, ANY_DEPTH):
            break
        prefix += 1
    fixed = 0 if segments and segments[-1] == ANY_DEPTH else 1
    return literals, prefix, fixed, -sum(1 for s in segments if s == WILDCARD)


@dataclass(frozen=True, slots=True)
class Subject:
    """Who a request comes from: a name, whether it was proven, and the scopes of its token."""

    name: str
    #: True when a certificate or a token proved the name.
    authenticated: bool = False
    #: The token's scopes; None when nothing narrows (no token, or a token without ``scope``).
    scopes: Scopes | None = None
    #: How the name was proven: "certificate", "token", "secret" (a device), or "" (not at all).
    via: str = ""
    #: The Session stream the request came on ("" for a unary call or HTTP): an anonymous caller
    #: holds licences under it, and loses them when it ends (:mod:`gateway.engine.licensing`).
    session: str = ""


@dataclass(frozen=True, slots=True)
class Scope:
    """One scope of a token: ``OPERATION:SERVICE`` or ``OPERATION:SERVICE.PATH`` (a subtree)."""

    operation: str
    service: str
    path: tuple[str, ...]

    def covers(self, operation: Operation, service: str, path: str) -> bool:
        if self.operation not in (WILDCARD, operation.value) or self.service not in (WILDCARD, service):
            return False
        return path_matches((*self.path, ANY_DEPTH), path)


@dataclass(frozen=True, slots=True)
class Scopes:
    """The scopes of a token (its ``scope`` claim, space-separated as OAuth 2 writes it).

    ``read:scout1`` allows reading anything of scout1; ``write:scout1.speed``
    allows Sets of ``speed`` and below; ``*`` stands for every operation or
    every service (``read:*``), and a ``*`` segment in the path for one segment.
    """

    scopes: tuple[Scope, ...]
    text: str = field(default="", compare=False)

    @classmethod
    def parse(cls, text: str) -> Scopes:
        """Parse a ``scope`` claim; InvalidArgument naming the scope that is wrong."""
        scopes = []
        for word in text.split():
            operation, colon, target = word.partition(":")
            if not colon or not target:
                raise InvalidArgument(f"scope {word!r}: expected OPERATION:SERVICE[.PATH], e.g. read:scout1")
            if operation != WILDCARD:
                parse_operation(operation, f"scope {word!r}")
            service, _, path = target.partition(".")
            if service != WILDCARD:
                try:
                    validate_service_name(service)
                except InvalidArgument as exc:
                    raise InvalidArgument(f"scope {word!r}: {exc.message}") from None
            segments = check_rule_path(path, f"scope {word!r}") if path else ()
            if ANY_DEPTH in segments:
                raise InvalidArgument(
                    f"scope {word!r}: a scope names a subtree already; drop the {ANY_DEPTH}"
                )
            scopes.append(Scope(operation, service, segments))
        return cls(tuple(scopes), text)

    def allow(self, operation: Operation, service: str, path: str) -> bool:
        return any(scope.covers(operation, service, path) for scope in self.scopes)


class Effect(enum.StrEnum):
    """What a rule decides."""

    PERMIT = "permit"
    DENY = "deny"


@dataclass(frozen=True, slots=True)
class Rule:
    """One ``[[rules]]`` entry, checked; ``index`` is its place in the config (from 0)."""

    index: int
    subjects: tuple[str, ...]
    service: str
    path: str
    operations: frozenset[Operation]
    effect: Effect
    segments: tuple[str, ...] = field(default=(), compare=False)

    @classmethod
    def build(
        cls,
        index: int,
        *,
        subject: str | Sequence[str],
        service: str = WILDCARD,
        path: str = ANY_DEPTH,
        operations: Iterable[str],
        effect: str,
    ) -> Rule:
        """A checked rule; InvalidArgument naming ``rules[index]`` and the key that is wrong."""
        where = f"rules[{index}]"
        subjects = (subject,) if isinstance(subject, str) else tuple(subject)
        if not subjects or any(not isinstance(s, str) or not s for s in subjects):
            raise InvalidArgument(f"{where}.subject: expected a name, * or a list of names")
        if service != WILDCARD:
            try:
                validate_service_name(service)
            except InvalidArgument as exc:
                raise InvalidArgument(f"{where}.service: {exc.message}") from None
        segments = check_rule_path(path, f"{where}.path")
        ops = frozenset(parse_operation(op, f"{where}.operations") for op in operations)
        if not ops:
            raise InvalidArgument(f"{where}.operations: name at least one operation")
        try:
            kind = Effect(effect)
        except ValueError:
            raise InvalidArgument(f"{where}.effect: expected permit or deny, got {effect!r}") from None
        return cls(index, subjects, service, path, ops, kind, segments)

    @property
    def text(self) -> str:
        """The rule as the config would write it, for messages."""
        subject = self.subjects[0] if len(self.subjects) == 1 else "[" + ", ".join(self.subjects) + "]"
        ops = ",".join(op.value for op in Operation if op in self.operations)
        return f"{self.effect.value} {subject} {ops} {self.service}/{self.path}"

    def matches(self, subject: str, service: str, path: str, operation: Operation) -> bool:
        return (
            operation in self.operations
            and (WILDCARD in self.subjects or subject in self.subjects)
            and self.service in (WILDCARD, service)
            and path_matches(self.segments, path)
        )

    def specificity(self, subject: str) -> tuple[int, tuple[int, int, int, int], int]:
        """Larger is more specific; see the module docstring."""
        return (
            0 if self.service == WILDCARD else 1,
            path_specificity(self.segments),
            1 if subject in self.subjects else 0,
        )


@dataclass(frozen=True, slots=True)
class Decision:
    """The outcome of a check: allowed or not, and the rule that decided (None: implicit or no rules)."""

    allowed: bool
    rule: Rule | None
    #: Why, for a refusal's message.
    reason: str


def _where(service: str, path: str) -> str:
    return f"{service}/{path}" if path else service


class Rules:
    """The configured ``[[rules]]``; with none, everything is allowed (scopes still narrow)."""

    def __init__(self, rules: Sequence[Rule] = ()) -> None:
        self.rules = tuple(rules)
        self._memo: dict[tuple[str, str, str, Operation], Decision] = {}

    def __bool__(self) -> bool:
        return bool(self.rules)

    @property
    def remembered(self) -> int:
        """Decisions remembered now (at most a few thousand)."""
        return len(self._memo)

    def decide(self, subject: str, service: str, path: str, operation: Operation) -> Decision:
        """What the rules say about ``subject`` doing ``operation`` on ``service``/``path`` (no scopes)."""
        key = (subject, service, path, operation)
        found = self._memo.get(key)
        if found is not None:
            return found
        found = self._decide(subject, service, path, operation)
        if len(self._memo) >= _CACHE_SIZE:
            self._memo.clear()
        self._memo[key] = found
        return found

    def _decide(self, subject: str, service: str, path: str, operation: Operation) -> Decision:
        if not self.rules:
            return Decision(True, None, "no rules are configured")
        best: Rule | None = None
        best_rank: tuple[int, tuple[int, int, int, int], int] | None = None
        for rule in self.rules:
            if not rule.matches(subject, service, path, operation):
                continue
            rank = rule.specificity(subject)
            # At the same specificity a deny replaces a permit (deny wins), never the other way.
            if (
                best is None
                or best_rank is None
                or rank > best_rank
                or (rank == best_rank and rule.effect is Effect.DENY and best.effect is Effect.PERMIT)
            ):
                best, best_rank = rule, rank
        if best is None:
            return Decision(False, None, "no rule permits it (implicit deny)")
        if best.effect is Effect.DENY:
            return Decision(False, best, f"refused by rules[{best.index}] ({best.text})")
        return Decision(True, best, f"permitted by rules[{best.index}] ({best.text})")

    def check(self, subject: Subject, service: str, path: str, operation: Operation) -> Decision:
        """:meth:`decide`, then the subject's token scopes narrow an allowed request."""
        decision = self.decide(subject.name, service, path, operation)
        if (
            decision.allowed
            and subject.scopes is not None
            and not subject.scopes.allow(operation, service, path)
        ):
            return Decision(
                False, None, f"the token's scopes ({subject.scopes.text or 'none'}) do not allow it"
            )
        return decision

    def require(self, subject: Subject, service: str, path: str, operation: Operation) -> None:
        """Raise :func:`refusal` unless :meth:`check` allows it."""
        decision = self.check(subject, service, path, operation)
        if not decision.allowed:
            raise refusal(subject, service, path, operation, decision)


def refusal(
    subject: Subject, service: str, path: str, operation: Operation, decision: Decision
) -> PropertyError:
    """A refused request's error: UNAUTHENTICATED when the caller proved no name, else PERMISSION_DENIED."""
    what = f"{operation.value} {_where(service, path)}"
    if not subject.authenticated:
        return Unauthenticated(
            f"{what}: not allowed without credentials (a client certificate or a bearer token):"
            f" {decision.reason}"
        )
    return PermissionDenied(f"{what}: {subject.name} may not: {decision.reason}")
