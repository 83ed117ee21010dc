"""Declared options: a dataclass's fields with their types, defaults and bounds, read by one parser.

The config's sections (``[gateway]``, ``[limits]``, ...) and the options of a proxy (a URL's
query, or the ``options`` table of its config entry) are each a frozen dataclass. A field
declares what it takes: its type and default, and for a number its bounds with :func:`option`
(a plain default takes any value of its type that is not negative, and a float must be finite).
:func:`read_options` checks a mapping against those fields, and says every problem in the
caller's own words (:class:`Wording`): what is wrong is always said the same way, where it is
is the caller's (``registry.timeout`` in a file, ``proxy option timeout`` in a URL).

Two ways of reading: a TOML table is typed already, so a value must have the field's type (an
integer is a number too; ``true`` is not an integer); a URL's query is text, so a string is
parsed as the field's type (``1``/``true``/``yes``/``on`` and ``0``/``false``/``no``/``off``
for true or false).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import Field, dataclass, field, fields
from typing import Any
from urllib.parse import parse_qsl, urlsplit

__all__ = ["NOT_NEGATIVE", "Bounds", "Wording", "convert", "option", "read_options", "shown", "url_options"]

#: Where a field's bounds are kept in its dataclass metadata.
_BOUNDS = "option bounds"
#: A value shown in an error longer than this is cut (a URL can carry a very long one).
_SHOWN = 40

_TYPE_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
_TRUE = frozenset({"1", "true", "yes", "on"})
_FALSE = frozenset({"0", "false", "no", "off", ""})


@dataclass(frozen=True, slots=True)
class Bounds:
    """The numbers an option takes: from ``low`` (excluded when ``above``) to ``high``, finite,
    and ``off`` beside them (a value that turns the feature off, e.g. a keep-alive of 0)."""

    low: float = 0.0
    high: float = math.inf
    above: bool = False
    off: float | None = None
    #: What the number counts, for the error text ("seconds"); empty for a plain count.
    unit: str = ""

    def problem(self, value: float) -> str | None:
        """What is wrong with ``value`` (e.g. "must be at least 1"); None when it is taken."""
        if value == self.off:
            return None
        above_low = value > self.low if self.above else value >= self.low
        if math.isfinite(value) and above_low and value <= self.high:
            return None
        unit = f" {self.unit}" if self.unit else ""
        if self.high != math.inf:
            lowest = f"more than {self.low:g} and at most" if self.above else f"from {self.low:g} to"
            besides = f" (or {self.off:g}: off)" if self.off is not None else ""
            return f"must be {lowest} {self.high:g}{unit}{besides}"
        if self.above and self.low == 0:
            return f"must be a positive number of {self.unit}" if self.unit else "must be a positive number"
        if self.above:
            return f"must be more than {self.low:g}{unit}"
        if not math.isfinite(value):
            return f"must be a finite number of {self.unit}" if self.unit else "must be a finite number"
        return "must not be negative" if self.low == 0 else f"must be at least {self.low:g}{unit}"


#: What a number option takes unless it says otherwise.
NOT_NEGATIVE = Bounds()


def option(
    default: Any,
    *,
    low: float = 0.0,
    high: float = math.inf,
    above: bool = False,
    off: float | None = None,
    unit: str = "",
) -> Any:
    """A dataclass field with ``default`` and the :class:`Bounds` its number must keep."""
    return field(default=default, metadata={_BOUNDS: Bounds(low, high, above, off, unit)})


@dataclass(frozen=True, slots=True)
class Wording:
    """How a caller says what is wrong, as ``str.format`` templates: ``unknown`` gets ``{key}``
    and ``{known}`` (the names taken, comma separated); ``bad`` gets ``{key}``, ``{raw}`` (the
    value given, as Python writes it, cut when long) and ``{why}`` (what is wrong). Both get the
    names handed to :func:`read_options` besides (``{where}``)."""

    unknown: str
    bad: str


def convert(value: Any, kind: type, *, text: bool = False) -> Any:
    """``value`` as ``kind`` (bool, int, float or str); ValueError saying what was expected.

    An int is taken as a float (made one); a bool is never taken as a number. With ``text``, a
    string is parsed as ``kind`` too.
    """
    if isinstance(value, kind) and not (kind is not bool and isinstance(value, bool)):
        return value
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if text and isinstance(value, str):
        word = value.strip().lower()
        if kind is bool and word in _TRUE | _FALSE:
            return word in _TRUE
        if kind in (int, float):
            try:
                return kind(word)
            except ValueError:
                pass
    raise ValueError(f"expected {_TYPE_NAMES[kind]}")


def shown(raw: Any) -> str:
    """``raw`` as an error message shows it: as Python writes it, a long string cut."""
    return repr(raw[:_SHOWN] if isinstance(raw, str | bytes) else raw)


def read_options(
    cls: type[Any],
    given: Mapping[str, Any],
    wording: Wording,
    *,
    text: bool = False,
    skip: Collection[str] = (),
    **names: str,
) -> tuple[dict[str, Any], list[str]]:
    """The values of ``given`` that ``cls``'s fields take, and a problem for each other key.

    Keys in ``skip`` are someone else's (left out, and named among the known ones). A field's
    type is its default's; one that is not a bool, int, float or str is not read here.
    """
    declared: dict[str, Field[Any]] = {f.name: f for f in fields(cls)}
    values: dict[str, Any] = {}
    problems: list[str] = []
    for key, raw in given.items():
        if key in skip:
            continue
        f = declared.get(key)
        kind = type(f.default) if f is not None else None
        if f is None or kind not in _TYPE_NAMES:
            known = ", ".join(dict.fromkeys([*declared, *skip]))  # a field read apart is named once
            problems.append(wording.unknown.format(key=key, known=known, **names))
            continue
        try:
            value = convert(raw, kind, text=text)
        except ValueError as exc:
            problems.append(wording.bad.format(key=key, raw=shown(raw), why=exc, **names))
            continue
        why = f.metadata.get(_BOUNDS, NOT_NEGATIVE).problem(value) if kind in (int, float) else None
        if why is not None:
            problems.append(wording.bad.format(key=key, raw=shown(raw), why=why, **names))
            continue
        values[key] = value
    return values, problems


def url_options(url: str, options: Mapping[str, Any]) -> dict[str, Any]:
    """The options of ``url``'s query (text), overridden by ``options`` (a config entry's table)."""
    merged: dict[str, Any] = dict(parse_qsl(urlsplit(url).query))
    merged.update(options)
    return merged
