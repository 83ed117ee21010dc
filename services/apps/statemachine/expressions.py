"""Chart expressions: a small, safe subset of Python syntax, checked when a chart is loaded.

Guards (``cond``), values (``expr``) and delays of a chart are text from whoever
Sets ``M.definition``, so they are never given to ``eval``. :func:`compile_expression`
parses the text with :mod:`ast` and accepts only the node types listed in
``_ALLOWED``: literals, names of chart variables, arithmetic, comparisons,
``and``/``or``/``not``, ``x if c else y``, indexing, tuples and lists, ``a.b``
on records (the event: ``_event.name``, ``_event.data``) and calls of the
functions in :data:`FUNCTIONS` by their bare name, ``In('state')`` and
``value('SERVICE/PATH')`` (the latest value of a property the machine follows: its
one argument must be written as text, so every property a chart reads is known at
load). Anything else (attribute
access on other values, lambdas, comprehensions, ``**``, keyword arguments,
names starting with ``__``) is refused at load time with the reason.

Evaluation is bounded too: every text or list an expression builds is at most
:data:`MAX_RESULT_LENGTH` long, so ``"x" * 10**9`` fails instead of eating memory.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.kernel.errors import InvalidArgument
from services.kernel.values import MAX_VALUE_LENGTH, Value, format_number, parse_number, parse_vector

__all__ = [
    "FUNCTIONS",
    "LITERAL_ARGUMENTS",
    "MAX_EXPRESSION_LENGTH",
    "MAX_RESULT_LENGTH",
    "NOT_AN_EXPRESSION",
    "EvaluationError",
    "Expression",
    "Record",
    "check_size",
    "compile_expression",
    "format_chart_value",
    "parse_chart_value",
]

#: Longest expression text; a guard or a value is one line of a chart, not a program.
MAX_EXPRESSION_LENGTH = 2000
#: Most syntax nodes in one expression.
MAX_NODES = 400
#: Longest text, list or tuple an expression may build (the longest value a property takes).
MAX_RESULT_LENGTH = MAX_VALUE_LENGTH


#: How the refusal of text that does not parse as an expression starts.
NOT_AN_EXPRESSION = "not a valid expression"


class EvaluationError(Exception):
    """An expression failed while running (an undefined name, a type mismatch): error.execution."""


@dataclass(frozen=True, slots=True)
class Record:
    """A value whose fields an expression reads with ``a.b`` (the current event: ``_event.name``)."""

    fields: Mapping[str, Any]

    def field(self, name: str) -> Any:
        if name not in self.fields:
            raise EvaluationError(f"no field {name!r} (there are: {', '.join(sorted(self.fields))})")
        return self.fields[name]


def _number(x: Any) -> float:
    if isinstance(x, bool):
        return 1.0 if x else 0.0
    if isinstance(x, int | float):
        return float(x)
    if isinstance(x, str):
        return parse_number(x)
    raise EvaluationError(f"number() of a {type(x).__name__}")


def _vector(x: Any) -> tuple[float, ...]:
    if isinstance(x, str):
        return tuple(float(v) for v in parse_vector(x))
    if isinstance(x, list | tuple):
        return tuple(_number(v) for v in x)
    raise EvaluationError(f"vector() of a {type(x).__name__}")


def _distance(a: Any, b: Any) -> float:
    """Euclidean distance over the elements both have (a 6-vector pose and an (x y) waypoint: the plane)."""
    va, vb = _vector(a), _vector(b)
    n = min(len(va), len(vb))
    if n == 0:
        raise EvaluationError("distance() of an empty vector")
    return math.sqrt(sum((va[i] - vb[i]) ** 2 for i in range(n)))


def _marker(location: Any) -> str:
    """A target marker for ``behaviors.moveto``: ``<marker><location>(x y)</location></marker>``."""
    return f"<marker><location>{format_chart_value(_vector(location))}</location></marker>"


def _text(x: Any) -> str:
    return format_chart_value(x)


def _len(x: Any) -> int:
    if isinstance(x, str | list | tuple):
        return len(x)
    raise EvaluationError(f"len() of a {type(x).__name__}")


def _has_field(x: Any, name: Any) -> bool:
    """``hasattr(_event, 'sendid')``: whether a record (or a mapping) has the field."""
    if isinstance(x, Record):
        return name in x.fields
    return isinstance(x, dict) and name in x


def _min_max(pick: Callable[..., Any]) -> Callable[..., Any]:
    def chosen(*args: Any) -> Any:
        items = args[0] if len(args) == 1 and isinstance(args[0], list | tuple) else args
        if not items:
            raise EvaluationError(f"{pick.__name__}() of nothing")
        return pick(items)

    return chosen


#: The functions an expression may call, by bare name (``In`` is added per machine).
FUNCTIONS: dict[str, Callable[..., Any]] = {
    "abs": lambda x: abs(_number(x)),
    "round": lambda x, n=0: round(_number(x), int(n)),
    "min": _min_max(min),
    "max": _min_max(max),
    "len": _len,
    "number": _number,
    "int": lambda x: int(_number(x)),
    "text": _text,
    "vector": _vector,
    "distance": _distance,
    "marker": _marker,
    "hasattr": _has_field,
}

#: Functions whose arguments must be written as text (literals), with how many they take: the
#: chart is checked against them at load (``In``: a state the chart has; ``value``: a property
#: the machine follows while it runs).
LITERAL_ARGUMENTS: dict[str, int] = {"value": 1}

_BINARY: dict[type[ast.operator], Callable[[Any, Any], Any]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
    ast.FloorDiv: operator.floordiv,
    ast.Mod: operator.mod,
}
_COMPARE: dict[type[ast.cmpop], Callable[[Any, Any], Any]] = {
    ast.Eq: operator.eq,
    ast.NotEq: operator.ne,
    ast.Lt: operator.lt,
    ast.LtE: operator.le,
    ast.Gt: operator.gt,
    ast.GtE: operator.ge,
    ast.In: lambda a, b: a in b,
    ast.NotIn: lambda a, b: a not in b,
    ast.Is: operator.is_,
    ast.IsNot: operator.is_not,
}
_ALLOWED: tuple[type[ast.AST], ...] = (
    ast.Expression,
    ast.Constant,
    ast.Name,
    ast.Load,
    ast.Tuple,
    ast.List,
    ast.BinOp,
    ast.UnaryOp,
    ast.BoolOp,
    ast.Compare,
    ast.IfExp,
    ast.Subscript,
    ast.Slice,
    ast.Attribute,
    ast.Call,
    ast.And,
    ast.Or,
    ast.Not,
    ast.USub,
    ast.UAdd,
    *_BINARY,
    *_COMPARE,
)


def _refuse(node: ast.AST, why: str) -> InvalidArgument:
    col = getattr(node, "col_offset", None)
    where = f" at column {col + 1}" if col is not None else ""
    return InvalidArgument(f"{why}{where}")


def _check(tree: ast.Expression, functions: Sequence[str]) -> None:
    for count, node in enumerate(ast.walk(tree), 1):
        if count > MAX_NODES:
            raise InvalidArgument(f"the expression is too complex (more than {MAX_NODES} parts)")
        if not isinstance(node, _ALLOWED):
            raise _refuse(node, f"{type(node).__name__} is not allowed in a chart expression")
        if isinstance(node, ast.Constant) and not isinstance(node.value, int | float | str | bool | None):
            raise _refuse(node, f"a {type(node.value).__name__} literal is not allowed")
        if isinstance(node, ast.Constant) and isinstance(node.value, int) and abs(node.value) > 2**63 - 1:
            raise _refuse(node, "an integer beyond 64 bits is not allowed")
        if isinstance(node, ast.Name) and node.id.startswith("__"):
            raise _refuse(node, f"the name {node.id!r} is not allowed")
        if isinstance(node, ast.Attribute) and node.attr.startswith("_"):
            raise _refuse(node, f"the field {node.attr!r} is not allowed")
        if isinstance(node, ast.Call):
            if isinstance(node.func, ast.Attribute) and node.func.attr == "get" and 1 <= len(node.args) <= 2:
                pass  # a record's field, or a default: _event.data.get('Var1', 0)
            elif not isinstance(node.func, ast.Name) or node.func.id not in functions:
                raise _refuse(
                    node, f"only these functions can be called: {', '.join(functions)} (and X.get(field))"
                )
            if node.keywords or any(isinstance(a, ast.Starred) for a in node.args):
                raise _refuse(node, "functions take positional arguments only")
            called = node.func.id if isinstance(node.func, ast.Name) else ""
            wanted = LITERAL_ARGUMENTS.get(called)
            if wanted is not None and (
                len(node.args) != wanted
                or not all(isinstance(a, ast.Constant) and isinstance(a.value, str) for a in node.args)
            ):
                raise _refuse(
                    node,
                    f"{called}() takes the property written as text, like "
                    f"{called}('thermo1/data'), so that it is known when the chart is loaded",
                )


class Expression:
    """A checked expression; :meth:`evaluate` runs it against the chart's variables."""

    __slots__ = ("_error", "_tree", "text")

    def __init__(self, text: str, tree: ast.Expression, error: str = "") -> None:
        self.text = text
        self._tree = tree
        self._error = error

    @classmethod
    def failing(cls, text: str, why: str) -> Expression:
        """Text that does not parse: every evaluation is an EvaluationError saying ``why``."""
        return cls(text, ast.Expression(body=ast.Constant(None)), why)

    def __repr__(self) -> str:
        return f"Expression({self.text!r})"

    def names(self) -> set[str]:
        """The variable and function names the expression reads."""
        return {n.id for n in ast.walk(self._tree) if isinstance(n, ast.Name)}

    def text_arguments(self, function: str) -> list[str]:
        """The arguments written as text in calls of ``function`` (``In('goto')``: ``goto``)."""
        return [
            a.value
            for n in ast.walk(self._tree)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == function
            for a in n.args
            if isinstance(a, ast.Constant) and isinstance(a.value, str)
        ]

    def evaluate(self, variables: Mapping[str, Any], functions: Mapping[str, Callable[..., Any]]) -> Any:
        """The value; EvaluationError when it cannot be computed."""
        if self._error:
            raise EvaluationError(f"{self.text[:60]!r}: {self._error}")
        try:
            return _Evaluator(variables, functions).run(self._tree.body)
        except EvaluationError:
            raise
        except InvalidArgument as e:
            raise EvaluationError(e.message) from None
        except (ArithmeticError, TypeError, ValueError, IndexError, KeyError, RecursionError) as e:
            raise EvaluationError(f"{type(e).__name__}: {e}") from None


def compile_expression(text: str, functions: Sequence[str] = (*FUNCTIONS, "In", "value")) -> Expression:
    """Parse and check ``text``; InvalidArgument saying what is not allowed."""
    if len(text) > MAX_EXPRESSION_LENGTH:
        raise InvalidArgument(f"the expression is longer than {MAX_EXPRESSION_LENGTH} characters")
    source = text.strip()
    if not source:
        raise InvalidArgument("the expression is empty")
    try:
        tree = ast.parse(source, mode="eval")
    except SyntaxError as e:
        raise InvalidArgument(f"{NOT_AN_EXPRESSION}: {e.msg} (column {e.offset or 0})") from None
    except (ValueError, RecursionError, MemoryError) as e:
        raise InvalidArgument(f"{NOT_AN_EXPRESSION}: {e}") from None
    _check(tree, functions)
    return Expression(source, tree)


#: Integers stay within 64 bits: a chain of products cannot grow a number without bound.
_MAX_INT = 2**63 - 1


def _bounded(value: Any) -> Any:
    if isinstance(value, str | list | tuple) and len(value) > MAX_RESULT_LENGTH:
        raise EvaluationError(f"the result would be longer than {MAX_RESULT_LENGTH}")
    if isinstance(value, float) and not math.isfinite(value):
        raise EvaluationError("the result is not a finite number")
    if isinstance(value, int) and not -_MAX_INT <= value <= _MAX_INT:
        raise EvaluationError("the result is an integer beyond 64 bits")
    return value


class _Evaluator:
    def __init__(self, variables: Mapping[str, Any], functions: Mapping[str, Callable[..., Any]]) -> None:
        self.variables = variables
        self.functions = functions

    def run(self, node: ast.expr) -> Any:
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.Name):
            return self._name(node.id)
        if isinstance(node, ast.Tuple):
            return tuple(self.run(e) for e in node.elts)
        if isinstance(node, ast.List):
            return [self.run(e) for e in node.elts]
        if isinstance(node, ast.BinOp):
            left, right = self.run(node.left), self.run(node.right)
            self._check_repeat(node.op, left, right)
            return _bounded(_BINARY[type(node.op)](left, right))
        if isinstance(node, ast.UnaryOp):
            operand = self.run(node.operand)
            if isinstance(node.op, ast.Not):
                return not operand
            if not isinstance(operand, int | float):
                raise EvaluationError(f"a sign before a {type(operand).__name__}")
            return -operand if isinstance(node.op, ast.USub) else +operand
        if isinstance(node, ast.BoolOp):
            return self._bool_op(node)
        if isinstance(node, ast.Compare):
            left = self.run(node.left)
            for op, comparator in zip(node.ops, node.comparators, strict=True):
                right = self.run(comparator)
                if not _COMPARE[type(op)](left, right):
                    return False
                left = right
            return True
        if isinstance(node, ast.IfExp):
            return self.run(node.body) if self.run(node.test) else self.run(node.orelse)
        if isinstance(node, ast.Subscript):
            return self._subscript(node)
        if isinstance(node, ast.Attribute):
            value = self.run(node.value)
            if not isinstance(value, Record):
                raise EvaluationError(f"a {type(value).__name__} has no field {node.attr!r}")
            return value.field(node.attr)
        if isinstance(node, ast.Call):
            if isinstance(node.func, ast.Attribute):  # X.get(field[, default]): checked at load time
                return self._get(node.func.value, node.args)
            assert isinstance(node.func, ast.Name)  # checked at load time
            function = self.functions.get(node.func.id)
            if function is None:
                raise EvaluationError(f"no function {node.func.id!r}")
            return _bounded(function(*(self.run(a) for a in node.args)))
        raise EvaluationError(f"{type(node).__name__} cannot be evaluated")  # refused at load time

    def _name(self, name: str) -> Any:
        if name in self.variables:
            return self.variables[name]
        if name in ("true", "True"):
            return True
        if name in ("false", "False"):
            return False
        if name in ("null", "None"):
            return None
        raise EvaluationError(f"name {name!r} is not defined")

    def _get(self, of: ast.expr, args: list[ast.expr]) -> Any:
        value = self.run(of)
        key = self.run(args[0])
        default = self.run(args[1]) if len(args) > 1 else None
        if isinstance(value, Record):
            return value.fields.get(key, default)
        if isinstance(value, dict):
            return value.get(key, default)
        raise EvaluationError(f"a {type(value).__name__} has no fields to get")

    def _bool_op(self, node: ast.BoolOp) -> Any:
        value: Any = None
        for operand in node.values:
            value = self.run(operand)
            if isinstance(node.op, ast.And) and not value:
                return value
            if isinstance(node.op, ast.Or) and value:
                return value
        return value

    def _subscript(self, node: ast.Subscript) -> Any:
        value = self.run(node.value)
        if isinstance(node.slice, ast.Slice):
            bounds = (node.slice.lower, node.slice.upper, node.slice.step)
            parts = [None if p is None else self.run(p) for p in bounds]
            return value[slice(*parts)]
        key = self.run(node.slice)
        if isinstance(value, Record):
            return value.field(str(key))
        if isinstance(value, dict):
            return value[key]
        if not isinstance(value, str | list | tuple):
            raise EvaluationError(f"a {type(value).__name__} cannot be indexed")
        if isinstance(key, bool) or not isinstance(key, int):
            raise EvaluationError(f"an index must be an integer, not a {type(key).__name__}")
        return value[key]

    @staticmethod
    def _check_repeat(op: ast.operator, left: Any, right: Any) -> None:
        """``"ab" * n`` and ``[0] * n``: refuse before building something too long.

        ``%`` is the remainder of two numbers only: on a text it would be printf-style
        formatting, whose width or precision (``'%999999999d' % 1``) builds a string of any
        size before its length could be checked.
        """
        if isinstance(op, ast.Mod) and not (isinstance(left, int | float) and isinstance(right, int | float)):
            kinds = f"a {type(left).__name__} and a {type(right).__name__}"
            raise EvaluationError(f"% takes two numbers (the remainder), not {kinds}")
        if not isinstance(op, ast.Mult):
            return
        for seq, count in ((left, right), (right, left)):
            if (
                isinstance(seq, str | list | tuple)
                and isinstance(count, int)
                and len(seq) * max(count, 0) > MAX_RESULT_LENGTH
            ):
                raise EvaluationError(f"the result would be longer than {MAX_RESULT_LENGTH}")


#: Deepest nesting of lists in a chart variable or an event's data.
MAX_VALUE_DEPTH = 32


def check_size(value: Any) -> Any:
    """``value`` when it may be kept in a chart variable; EvaluationError when it is too big.

    Lists may share items (``w = [w, w]`` in a loop), so a value is measured as it would be
    written out: at most :data:`MAX_RESULT_LENGTH` items and characters all told, nested at
    most :data:`MAX_VALUE_DEPTH` levels. A shared list is measured once (its size remembered),
    so the check costs the number of distinct lists, not the size written out.
    """
    sizes: dict[int, int] = {}

    def size(item: Any, depth: int) -> int:
        if depth > MAX_VALUE_DEPTH:
            raise EvaluationError(f"the value nests deeper than {MAX_VALUE_DEPTH} levels")
        if isinstance(item, str):
            return len(item)
        if not isinstance(item, list | tuple | Record):
            return 1
        known = sizes.get(id(item))
        if known is not None:
            return known
        total = 1
        for inner in item.fields.values() if isinstance(item, Record) else item:
            total += size(inner, depth + 1)
            if total > MAX_RESULT_LENGTH:
                raise EvaluationError(f"the value would be longer than {MAX_RESULT_LENGTH} written out")
        sizes[id(item)] = total
        return total

    if size(value, 0) > MAX_RESULT_LENGTH:
        raise EvaluationError(f"the value would be longer than {MAX_RESULT_LENGTH} written out")
    return value


def parse_chart_value(text: Value) -> Any:
    """A property's text as a chart value: a number, a vector (as a tuple of numbers), or the text itself.

    A binary value stays bytes (a chart may compare it or take its ``len``).
    """
    if isinstance(text, bytes):
        return text
    stripped = text.strip()
    if stripped.startswith("(") and stripped.endswith(")"):
        try:
            return tuple(float(v) for v in parse_vector(stripped))
        except InvalidArgument:
            return text
    try:
        number = parse_number(stripped)
    except InvalidArgument:
        return text
    integral = number.is_integer() and "." not in stripped and "e" not in stripped.lower()
    return int(number) if integral else number


def format_chart_value(value: Any) -> str:
    """A chart value as property text: ``2``, ``0.5``, ``(1 2)``, ``((1 2) (3 4))``, ``true``, or the text."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return format_number(value)
    if value is None:
        return ""
    if isinstance(value, list | tuple):
        return "(" + " ".join(format_chart_value(v) for v in value) + ")"
    if isinstance(value, Record):
        return "(" + " ".join(f"({k} {format_chart_value(v)})" for k, v in value.fields.items()) + ")"
    return str(value)
