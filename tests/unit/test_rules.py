"""The rule engine: path patterns, specificity, deny wins, implicit deny, scopes only narrow."""

from __future__ import annotations

import pytest

from gateway.engine.rules import (
    Operation,
    Rule,
    Rules,
    Scopes,
    Subject,
    check_rule_path,
    path_matches,
    path_specificity,
    refusal,
)
from services.kernel.errors import Code, InvalidArgument, PermissionDenied, Unauthenticated

READ, WRITE, INVOKE = Operation.READ, Operation.WRITE, Operation.INVOKE
ALICE = Subject("alice", authenticated=True, via="token")
BOB = Subject("bob", authenticated=True, via="certificate")
NOBODY = Subject("anonymous")


def rule(index: int, subject: str | list[str], service: str, path: str, ops: str, effect: str) -> Rule:  # noqa: PLR0917
    return Rule.build(
        index, subject=subject, service=service, path=path, operations=ops.split(","), effect=effect
    )


@pytest.mark.parametrize(
    ("pattern", "path", "expected"),
    [
        ("location", "location", True),
        ("location", "location.x", False),
        ("location.*", "location.x", True),
        ("location.*", "location", False),
        ("location.*", "location.x.y", False),
        ("location.**", "location", True),
        ("location.**", "location.x", True),
        ("location.**", "location.x.y", True),
        ("location.**", "locations", False),
        ("*.speed", "arm.speed", True),
        ("*.speed", "speed", False),
        ("**", "", True),
        ("**", "a.b.c", True),
        ("location", "", False),
        ("*.**", "", False),
        ("*.**", "a", True),
    ],
)
def test_path_patterns(pattern: str, path: str, expected: bool) -> None:
    assert path_matches(check_rule_path(pattern, "test"), path) is expected


@pytest.mark.parametrize("bad", ["a.**.b", "a..b", "a*", "**.x", "a b"])
def test_bad_rule_paths_are_refused_naming_the_rule(bad: str) -> None:
    with pytest.raises(InvalidArgument, match=r"rules\[3\]\.path"):
        rule(3, "alice", "scout1", bad, "read", "permit")


def test_bad_operations_effects_subjects_and_services_are_refused() -> None:
    with pytest.raises(InvalidArgument, match=r"rules\[0\]\.operations: unknown operation 'delete'"):
        rule(0, "alice", "*", "**", "delete", "permit")
    with pytest.raises(InvalidArgument, match=r"rules\[1\]\.effect: expected permit or deny"):
        rule(1, "alice", "*", "**", "read", "allow")
    with pytest.raises(InvalidArgument, match=r"rules\[2\]\.subject"):
        Rule.build(2, subject=[], operations=["read"], effect="permit")
    with pytest.raises(InvalidArgument, match=r"rules\[4\]\.service"):
        rule(4, "alice", "scout 1", "**", "read", "permit")
    with pytest.raises(InvalidArgument, match=r"rules\[5\]\.operations: name at least one"):
        Rule.build(5, subject="alice", operations=[], effect="permit")


def test_specificity_orders_literals_then_prefix_then_fixed_depth_then_fewer_stars() -> None:
    def spec(p: str) -> tuple[int, int, int, int]:
        return path_specificity(check_rule_path(p, "t"))

    assert spec("a.b.c") > spec("a.b.**") > spec("a.*.c") > spec("a.*.*") > spec("a.**") > spec("**")
    assert spec("a.b.*") > spec("a.*.b")  # same literals, longer literal prefix
    assert spec("a.*") > spec("a.**")  # same literals and prefix: a fixed depth beats any depth
    assert spec("a.*") > spec("a.*.*")  # then fewer * segments


def test_no_rules_allows_everything() -> None:
    rules = Rules()
    assert not rules
    for op in Operation:
        assert rules.check(NOBODY, "scout1", "location", op).allowed


def test_implicit_deny_when_any_rule_is_configured() -> None:
    rules = Rules([rule(0, "alice", "scout1", "**", "read", "permit")])
    decision = rules.check(BOB, "scout1", "location", READ)
    assert not decision.allowed and decision.rule is None
    assert "implicit deny" in decision.reason
    assert not rules.check(ALICE, "scout1", "location", WRITE).allowed
    assert not rules.check(ALICE, "light1", "switch", READ).allowed
    assert rules.check(ALICE, "scout1", "location", READ).allowed


def test_most_specific_path_wins_either_way() -> None:
    rules = Rules(
        [
            rule(0, "*", "scout1", "**", "read,write", "permit"),
            rule(1, "*", "scout1", "behaviors.**", "write", "deny"),
            rule(2, "*", "scout1", "behaviors.stop", "write", "permit"),
        ]
    )
    assert rules.check(ALICE, "scout1", "speed", WRITE).allowed
    refused = rules.check(ALICE, "scout1", "behaviors.go", WRITE)
    assert not refused.allowed and refused.rule is not None and refused.rule.index == 1
    assert rules.check(ALICE, "scout1", "behaviors.stop", WRITE).allowed


def test_a_named_service_beats_a_wildcard_service_whatever_the_path() -> None:
    rules = Rules(
        [
            rule(0, "*", "*", "location.x", "read", "deny"),
            rule(1, "*", "scout1", "**", "read", "permit"),
        ]
    )
    assert rules.check(ALICE, "scout1", "location.x", READ).allowed
    assert not rules.check(ALICE, "scout2", "location.x", READ).allowed


def test_a_named_subject_beats_a_wildcard_subject_at_the_same_place() -> None:
    rules = Rules(
        [
            rule(0, "*", "vault", "**", "read", "deny"),
            rule(1, "alice", "vault", "**", "read", "permit"),
        ]
    )
    assert rules.check(ALICE, "vault", "code", READ).allowed
    assert not rules.check(BOB, "vault", "code", READ).allowed


def test_deny_beats_permit_at_the_same_specificity_in_either_order() -> None:
    for order in ((0, 1), (1, 0)):
        entries = [
            rule(0, "alice", "scout1", "speed", "write", "permit"),
            rule(1, "alice", "scout1", "speed", "write", "deny"),
        ]
        rules = Rules([entries[i] for i in order])
        decision = rules.check(ALICE, "scout1", "speed", WRITE)
        assert not decision.allowed
        assert decision.rule is not None and decision.rule.effect == "deny"


def test_a_list_of_subjects_and_operations() -> None:
    rules = Rules([rule(0, ["alice", "bob"], "scout1", "**", "read,invoke", "permit")])
    assert rules.check(ALICE, "scout1", "behaviors.go", INVOKE).allowed
    assert rules.check(BOB, "scout1", "location", READ).allowed
    assert not rules.check(BOB, "scout1", "speed", WRITE).allowed
    assert not rules.check(Subject("carol", True), "scout1", "location", READ).allowed


def test_describe_asks_about_the_service_itself_which_only_a_double_star_matches() -> None:
    rules = Rules(
        [
            rule(0, "alice", "scout1", "location.**", "read", "permit"),
            rule(1, "bob", "scout1", "**", "read", "permit"),
        ]
    )
    assert not rules.check(ALICE, "scout1", "", READ).allowed
    assert rules.check(BOB, "scout1", "", READ).allowed


def test_scopes_narrow_and_never_widen() -> None:
    rules = Rules(
        [
            rule(0, "alice", "scout1", "**", "read,write", "permit"),
            rule(1, "alice", "scout1", "secret", "read", "deny"),
        ]
    )
    narrowed = Subject("alice", True, Scopes.parse("read:scout1 write:scout1.speed"), "token")
    assert rules.check(narrowed, "scout1", "location.x", READ).allowed
    assert rules.check(narrowed, "scout1", "speed", WRITE).allowed
    assert rules.check(narrowed, "scout1", "speed.left", WRITE).allowed  # a scope names a subtree
    refused = rules.check(narrowed, "scout1", "location", WRITE)
    assert not refused.allowed and "scopes (read:scout1 write:scout1.speed)" in refused.reason
    # A scope cannot give what the rules refuse.
    wide = Subject("alice", True, Scopes.parse("*:*"), "token")
    assert not rules.check(wide, "scout1", "secret", READ).allowed
    assert not rules.check(wide, "light1", "switch", READ).allowed
    # Scopes narrow even where no rules are configured.
    assert not Rules().check(narrowed, "light1", "switch", READ).allowed
    assert Rules().check(narrowed, "scout1", "anything", READ).allowed
    # An empty scope claim allows nothing.
    assert not Rules().check(Subject("alice", True, Scopes.parse(""), "token"), "x", "y", READ).allowed


def test_scopes_with_wildcards() -> None:
    scopes = Scopes.parse("read:* invoke:scout1.behaviors.* *:light1")
    assert scopes.allow(READ, "anything", "a.b")
    assert scopes.allow(INVOKE, "scout1", "behaviors.go")
    assert not scopes.allow(INVOKE, "scout1", "teleop")
    assert scopes.allow(Operation.ADMIN, "light1", "x")


@pytest.mark.parametrize(
    "bad", ["read", "read:", "fly:scout1", "read:scout 1", "read:scout1.**", "read:a..b"]
)
def test_bad_scopes_are_refused(bad: str) -> None:
    with pytest.raises(InvalidArgument, match="scope"):
        Scopes.parse(bad)


def test_refusals_name_the_rule_and_pick_the_code_by_who_asked() -> None:
    rules = Rules(
        [
            rule(0, "*", "scout1", "**", "read", "permit"),
            rule(1, "*", "scout1", "speed", "write", "deny"),
        ]
    )
    decision = rules.check(ALICE, "scout1", "speed", WRITE)
    err = refusal(ALICE, "scout1", "speed", WRITE, decision)
    assert isinstance(err, PermissionDenied) and err.code == Code.PERMISSION_DENIED
    assert err.message == (
        "write scout1/speed: alice may not: refused by rules[1] (deny * write scout1/speed)"
    )
    anonymous = refusal(NOBODY, "scout1", "speed", WRITE, rules.check(NOBODY, "scout1", "speed", WRITE))
    assert isinstance(anonymous, Unauthenticated) and anonymous.code == Code.UNAUTHENTICATED
    assert "rules[1] (deny * write scout1/speed)" in anonymous.message
    with pytest.raises(PermissionDenied, match="implicit deny"):
        rules.require(ALICE, "light1", "switch", READ)


def test_decisions_are_remembered_but_bounded() -> None:
    rules = Rules([rule(0, "*", "*", "**", "read", "permit")])
    for i in range(10_000):
        assert rules.check(ALICE, "scout1", f"p{i}", READ).allowed
    assert rules.remembered <= 4096
