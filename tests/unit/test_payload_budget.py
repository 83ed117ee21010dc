"""The budget for large values held for readers: what counts, what does not fit, and the message."""

from __future__ import annotations

import pytest

from gateway.config import ConfigError, loads_config
from gateway.engine.listen.budget import COUNTED_BYTES, PayloadBudget
from services.kernel.errors import Code


def test_large_values_count_until_given_back_and_one_past_the_limit_does_not_fit() -> None:
    budget = PayloadBudget(3 * COUNTED_BYTES)
    assert budget.take(2 * COUNTED_BYTES)
    assert not budget.take(2 * COUNTED_BYTES)
    assert budget.held == 2 * COUNTED_BYTES  # a value that did not fit counts nothing
    assert budget.take(COUNTED_BYTES)
    budget.give_back(2 * COUNTED_BYTES)
    budget.give_back(COUNTED_BYTES)
    assert budget.held == 0
    assert budget.take(3 * COUNTED_BYTES)


def test_small_values_always_fit_and_never_count() -> None:
    budget = PayloadBudget(COUNTED_BYTES)
    assert budget.take(COUNTED_BYTES)
    assert budget.take(COUNTED_BYTES - 1)
    budget.give_back(COUNTED_BYTES - 1)
    assert budget.held == COUNTED_BYTES


def test_a_refusal_is_resource_exhausted_naming_the_limit_and_the_sizes() -> None:
    budget = PayloadBudget(COUNTED_BYTES)
    err = budget.refusal(5_000_000, "Listen")
    assert err.code is Code.RESOURCE_EXHAUSTED
    assert "limits.max_pending_binary" in err.message
    assert "5000000 bytes" in err.message and f"({COUNTED_BYTES} bytes" in err.message


def test_the_budget_is_read_from_limits_and_must_be_positive() -> None:
    assert loads_config("[limits]\nmax_pending_binary = 1048576\n").limits.max_pending_binary == 1048576
    with pytest.raises(ConfigError, match=r"limits\.max_pending_binary: must be at least 1"):
        loads_config("[limits]\nmax_pending_binary = 0\n")
