"""Chart expressions: what a guard or a value may say, and what is refused when the chart is loaded."""

from __future__ import annotations

from typing import Any

import pytest

from services.apps.statemachine.expressions import (
    FUNCTIONS,
    EvaluationError,
    Record,
    check_size,
    compile_expression,
    format_chart_value,
    parse_chart_value,
)
from services.kernel.errors import InvalidArgument


def run(source: str, /, **variables: Any) -> Any:
    return compile_expression(source).evaluate(variables, FUNCTIONS)


@pytest.mark.parametrize(
    ("text", "variables", "expected"),
    [
        ("1 + 2 * 3", {}, 7),
        ("(i + 1) % len(w)", {"i": 2, "w": [1, 2, 3]}, 0),
        ("t > 30 and not stopped", {"t": 31.5, "stopped": False}, True),
        ("distance(pose, (3, 4)) < 0.2", {"pose": (3.1, 4.0, 0, 0, 0, 1.5)}, True),
        ("marker(w[1])", {"w": [(0, 0), (2, 2.5)]}, "<marker><location>(2 2.5)</location></marker>"),
        (
            "_event.data.code == 'NOT_FOUND'",
            {"_event": Record({"data": Record({"code": "NOT_FOUND"})})},
            True,
        ),
        ("'a' if x in (1, 2) else 'b'", {"x": 3}, "b"),
        ("max(number('2.5'), 1) - abs(-1)", {}, 1.5),
        ("w[-1][0]", {"w": [(1, 2), (5, 6)]}, 5),
        ("true and not false", {}, True),
    ],
)
def test_allowed_expressions_evaluate(text: str, variables: dict[str, Any], expected: Any) -> None:
    assert run(text, **variables) == expected


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("__import__('os').system('id')", "only these functions"),
        ("__import__", "'__import__'"),
        ("().__class__.__bases__", "'__bases__'"),
        ("x.__dict__", "'__dict__'"),
        ("open('/etc/passwd')", "only these functions"),
        ("(lambda: 1)", "Lambda"),
        ("[x for x in range(10)]", "ListComp"),
        ("2 ** 100000", "Pow"),
        ("len(x=1)", "positional"),
        ("f'{x}'", "JoinedStr"),
        ("x := 1", "not a valid expression"),
        ("a.b.c()", "only these functions"),
        ("1" * 3000, "longer than"),
        ("9" * 30, "64 bits"),
    ],
)
def test_unsafe_or_unsupported_expressions_are_refused_when_compiled(text: str, why: str) -> None:
    with pytest.raises(InvalidArgument) as refused:
        compile_expression(text)
    assert why in refused.value.message


@pytest.mark.parametrize(
    ("text", "variables", "why"),
    [
        ("'x' * 100000000", {}, "longer than"),
        ("n * n * n * n * n", {"n": 2**40}, "64 bits"),
        ("missing + 1", {}, "not defined"),
        ("1 / zero", {"zero": 0}, "ZeroDivisionError"),
        ("record.nothing", {"record": Record({"a": 1})}, "no field"),
        ("text.upper", {"text": "abc"}, "has no field"),
        ("w[5]", {"w": [1]}, "IndexError"),
        # % is the remainder of two numbers: on a text it would be printf-style formatting, whose
        # width and precision build a string of any size before its length could be checked.
        ("'%999999999d' % 1", {}, "% takes two numbers"),
        ("'%.999999999f' % 1.0", {}, "% takes two numbers"),
        ("'%s' % x", {"x": "a"}, "% takes two numbers"),
    ],
)
def test_runtime_failures_are_evaluation_errors_not_crashes(
    text: str, variables: dict[str, Any], why: str
) -> None:
    with pytest.raises(EvaluationError) as failed:
        run(text, **variables)
    assert why in str(failed.value)


def test_values_kept_in_variables_are_measured_as_written_out() -> None:
    w: list[object] = ["x" * 1000]
    for _ in range(6):
        w = [w, w]
    assert check_size(w) is w  # 64,000 characters shared 64 times: fits
    with pytest.raises(EvaluationError, match="longer than"):
        check_size([w, w])
    deep: list[object] = []
    for _ in range(40):
        deep = [deep]
    with pytest.raises(EvaluationError, match="deeper than"):
        check_size(deep)


def test_property_text_and_chart_values_convert_both_ways() -> None:
    assert parse_chart_value("(1 2.5 0)") == (1.0, 2.5, 0.0)
    assert parse_chart_value("30") == 30
    assert parse_chart_value("30.5") == 30.5
    assert parse_chart_value("<marker/>") == "<marker/>"
    assert format_chart_value((1.0, 2.5)) == "(1 2.5)"
    assert format_chart_value([(1, 2), (3, 4)]) == "((1 2) (3 4))"
    assert format_chart_value(True) == "true"
