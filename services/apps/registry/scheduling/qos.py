"""The QoS record the scheduler keeps per provider: normalised assessments from its consumers.

The seed's consumer rates each provider after the work on a normalised scale, 0 (useless) to
1 (perfect): ``B 0.86, C 0, D 0.94, E 0.82``. A release carries those as
``((B 0.86) (C 0) (D 0.94) (E 0.82))``; the record keeps, per provider, how many assessments
it had, their mean (what ranking uses) and the last one.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

from services.kernel.errors import InvalidArgument
from services.kernel.values import ValueFormatError, parse_list, parse_number

__all__ = ["MAX_QOS_PROVIDERS", "QosBook", "QosRecord", "parse_assessments"]

#: Providers whose record is kept; past it the one assessed longest ago is dropped (it ranks as
#: unknown again). Ten times the largest registry the benchmark runs.
MAX_QOS_PROVIDERS = 100_000


@dataclass(frozen=True, slots=True)
class QosRecord:
    """One provider's assessments: how many, their mean, the last one (each 0 to 1)."""

    count: int
    mean: float
    last: float

    def add(self, score: float) -> QosRecord:
        count = self.count + 1
        return QosRecord(count, self.mean + (score - self.mean) / count, score)


class QosBook:
    """Assessments per provider, bounded to ``limit`` providers (least recently assessed dropped)."""

    def __init__(self, limit: int = MAX_QOS_PROVIDERS) -> None:
        self._records: OrderedDict[str, QosRecord] = OrderedDict()
        self._limit = limit

    def record(self, provider: str, score: float) -> QosRecord:
        """Add one assessment of ``provider``; its new record."""
        old = self._records.pop(provider, None)
        new = old.add(score) if old is not None else QosRecord(1, score, score)
        self._records[provider] = new
        while len(self._records) > self._limit:
            self._records.popitem(last=False)
        return new

    def get(self, provider: str) -> QosRecord | None:
        return self._records.get(provider)

    def means(self) -> dict[str, float]:
        """The mean of every assessed provider."""
        return {name: r.mean for name, r in self._records.items()}

    def items(self) -> list[tuple[str, QosRecord]]:
        """(provider, record) in the order they were last assessed."""
        return list(self._records.items())


def _score(text: str, provider: str) -> float:
    try:
        value = parse_number(text)
    except ValueFormatError:
        value = math.nan
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise InvalidArgument(
            f"qos: the assessment of {provider} must be a number from 0 to 1, got {text[:32]!r}"
        )
    return value


def parse_assessments(text: str) -> dict[str, float]:
    """``((B 0.86) (C 0))`` as {provider: score}; each score 0 to 1, each provider once."""
    if not text.strip():
        return {}
    try:
        items = parse_list(text)
    except ValueFormatError as e:
        raise InvalidArgument(f"qos: {e.message}; expected ((provider score) ...)") from None
    found: dict[str, float] = {}
    for item in items:
        if not (isinstance(item, list) and len(item) == 2 and all(isinstance(x, str) for x in item)):
            raise InvalidArgument("qos: expected ((provider score) ...), e.g. ((B 0.86) (C 0))")
        provider, score = item
        if provider in found:
            raise InvalidArgument(f"qos: {provider} is assessed twice")
        found[provider] = _score(score, provider)
    return found
