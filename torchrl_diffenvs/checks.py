"""Value checks shared by the learners' settings and the training configuration.

Each check returns ``None`` for a valid value, else what was expected, so that callers can either
raise at once (a learner built from Python) or collect every problem of a configuration
(``sota_scripts/train.py`` reports them all in one error).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

__all__ = [
    "Check", "adam_betas", "boolean", "in_interval", "is_int", "is_number", "learning_rate", "nonnegative", "nonnegative_int", "one_of", "optional_positive",
    "positive", "positive_int",
]

Check = Callable[[object], "str | None"]


def is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def positive_int(value) -> str | None:
    return None if is_int(value) and value >= 1 else "expected an integer >= 1"


def nonnegative_int(value) -> str | None:
    return None if is_int(value) and value >= 0 else "expected an integer >= 0"


def positive(value) -> str | None:
    return None if is_number(value) and value > 0 else "expected a number > 0"


def learning_rate(value) -> str | None:
    return None if is_number(value) and value > 0 else "a learning rate must be a number > 0"


def nonnegative(value) -> str | None:
    return None if is_number(value) and value >= 0 else "expected a number >= 0"


def optional_positive(value) -> str | None:
    return None if value is None or (is_number(value) and value > 0) else "expected a number > 0, or null to disable it"


def in_interval(low: float, high: float, low_inclusive: bool = False) -> Check:
    """A number in ``[low, high]`` or ``(low, high]`` (``high`` is always inclusive)."""
    bracket = "[" if low_inclusive else "("

    def check(value) -> str | None:
        ok = is_number(value) and (value >= low if low_inclusive else value > low) and value <= high
        return None if ok else f"expected a number in {bracket}{low}, {high}]"

    return check


def one_of(choices: Sequence) -> Check:
    def check(value) -> str | None:
        return None if value in choices else f"valid: {', '.join(map(str, choices))}"

    return check


def adam_betas(value) -> str | None:
    ok = (
        isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2
        and all(is_number(b) and 0.0 <= b < 1.0 for b in value)
    )
    return None if ok else "expected two Adam betas in [0, 1), e.g. [0.7, 0.95]"


def boolean(value) -> str | None:
    return None if isinstance(value, bool) else "expected true or false"
