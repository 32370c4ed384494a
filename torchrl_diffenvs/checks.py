"""Value checks and typed settings shared by the learners, the training configuration and the demos.

Each check returns ``None`` for a valid value, else what was expected, so that callers can either
raise at once (a learner built from Python) or collect every problem of a configuration
(``sota_scripts/train.py`` reports them all in one error).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence

__all__ = [
    "Check", "Settings", "checked", "parse_cli", "adam_betas", "boolean", "in_interval", "is_int", "each", "is_number", "learning_rate", "nonnegative", "nonnegative_int", "one_of", "optional_positive",
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


def each(check: Check) -> Check:
    """Every element of a list passes ``check``."""

    def check_all(values) -> str | None:
        if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
            return "expected a list, e.g. [a,b]"
        for value in values:
            message = check(value)
            if message is not None:
                return f"element {value!r}: {message}"
        return None

    return check_all


def boolean(value) -> str | None:
    return None if isinstance(value, bool) else "expected true or false"


def checked(default, check: Check):
    """A settings field with its default and the check its values must pass (a list default
    stays a list, a tuple default a tuple)."""
    if isinstance(default, (list, tuple)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"check": check})
    return dataclasses.field(default=default, metadata={"check": check})


@dataclasses.dataclass(frozen=True)
class Settings:
    """Base of typed settings: a frozen dataclass whose fields carry their default and their
    check (`checked`). Building one checks every field (``ValueError`` naming each bad
    one); `problems` lists them without raising (the training script reports all at once).
    The learners' settings and the demos' arguments are such dataclasses."""

    @classmethod
    def problems(cls, values: Mapping, where: str = "") -> list[str]:
        """Every problem of ``values`` (unknown keys and values that fail their field's check)."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        problems = []
        for key, value in values.items():
            name = f"{where}{key}"
            if key not in fields:
                problems.append(f"{name}: unknown setting of {cls.__name__}; valid: {', '.join(fields)}")
                continue
            check = fields[key].metadata.get("check")
            message = None if check is None else check(value)
            if message is not None:
                problems.append(f"{name}={value!r}: {message}")
        if not problems:
            problems = cls.relation_problems({**cls.defaults(), **values}, where)
        return problems

    @classmethod
    def relation_problems(cls, values: Mapping, where: str = "") -> list[str]:
        """Problems between fields (each valid alone); override where settings constrain each other."""
        return []

    @classmethod
    def defaults(cls) -> dict:
        return {f.name: f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
                for f in dataclasses.fields(cls)}

    def __post_init__(self):
        problems = self.problems({f.name: getattr(self, f.name) for f in dataclasses.fields(self)})
        if problems:
            raise ValueError(f"{type(self).__name__}: " + "; ".join(problems))

    @classmethod
    def from_mapping(cls, values: Mapping) -> Settings:
        """Builds the settings from a mapping (e.g. a Hydra ``loss`` section without its networks);
        lists become tuples."""
        plain = {k: tuple(v) if isinstance(v, (list, tuple)) or type(v).__name__ == "ListConfig" else v
                 for k, v in values.items()}
        problems = cls.problems(plain)
        if problems:
            raise ValueError(f"{cls.__name__}: " + "; ".join(problems))
        return cls(**plain)


def parse_cli(settings_class: type[Settings], argv: Sequence[str] | None = None, usage: str = "") -> Settings:
    """Parses ``key=value`` command-line arguments into ``settings_class`` with OmegaConf (the
    configuration system behind the training script's Hydra): values are converted to the fields'
    types (lists as ``key=[1,2]``); unknown keys, values of the wrong type and failed checks stop
    the script with one clear message (``SystemExit``). Used by the demos and the benchmarks.
    """
    import sys

    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    argv = sys.argv[1:] if argv is None else list(argv)
    valid = settings_class.defaults()
    if any(item in ("-h", "--help") for item in argv):
        defaults = " ".join(f"{k}={v}" for k, v in valid.items())
        print((usage or "").rstrip() + f"\n\narguments (key=value), with their defaults: {defaults}")
        raise SystemExit(0)
    for item in argv:
        key, sep, _ = item.partition("=")
        if not sep or key not in valid:
            raise SystemExit(f"error: unknown argument {item!r}; valid keys (key=value): {', '.join(valid)}")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(settings_class), OmegaConf.from_dotlist(argv))
        values = OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as err:  # a value of the wrong type
        key = getattr(err, "full_key", None)
        raise SystemExit(f"error: {key}: {str(err).splitlines()[0]}" if key else f"error: {err}") from None
    try:
        return settings_class(**values)
    except ValueError as err:  # a field's check
        raise SystemExit(f"error: {err}") from None
