"""Typed, validated configs built from Hydra/OmegaConf mappings.

Every tunable figure of a task, observation or reward is a field of a frozen dataclass whose
``__post_init__`` validates it with the checks below. :func:`build` turns a mapping (a
``DictConfig`` group, say) into such a dataclass, recursing into dataclass-typed fields, and
raises :class:`ValueError` naming the offending key with its full path (``env.model.dt must be
a number > 0, got -1.0``) for a bad value, an unknown key or a missing one.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import typing
from collections.abc import Mapping
from typing import Any


def number(
    name: str, value, low: float = -math.inf, high: float = math.inf, open_low: bool = False
) -> float:
    """``value`` as a float in [low, high] ((low, high] if ``open_low``), else ValueError."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if not (ok and (value > low if open_low else value >= low) and value <= high):
        conditions = [f"{'>' if open_low else '>='} {low:g}"] if low > -math.inf else []
        conditions += [f"<= {high:g}"] if high < math.inf else []
        wanted = " ".join(["a finite number", " and ".join(conditions)]).strip()
        raise ValueError(f"{name} must be {wanted}, got {value!r}")
    return float(value)


def positive(name: str, value) -> float:
    """``value`` as a float > 0, else ValueError naming ``name``."""
    return number(name, value, low=0.0, open_low=True)


def integer(name: str, value, low: int = 0) -> int:
    """``value`` as an int >= ``low``, else ValueError naming ``name``."""
    if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def interval(
    name: str, value, low: float = -math.inf, high: float = math.inf
) -> tuple[float, float]:
    """``value`` as a pair (a, b) with low <= a <= b <= high, else ValueError naming ``name``."""
    if not isinstance(value, typing.Sequence) or isinstance(value, str) or len(value) != 2:
        raise ValueError(f"{name} must be a pair [low, high], got {value!r}")
    a, b = (number(f"{name}[{i}]", v, low=low, high=high) for i, v in enumerate(value))
    if a > b:
        raise ValueError(f"{name} must be a pair [low, high] with low <= high, got {list(value)!r}")
    return a, b


def vector(name: str, value, length: int | None = None) -> tuple[float, ...]:
    """``value`` as a tuple of finite floats (of ``length`` entries), else ValueError."""
    if not isinstance(value, typing.Sequence) or isinstance(value, str):
        raise ValueError(f"{name} must be a list of numbers, got {value!r}")
    if length is not None and len(value) != length:
        raise ValueError(f"{name} must have {length} entries, got {value!r}")
    return tuple(number(f"{name}[{i}]", v) for i, v in enumerate(value))


def choice(name: str, value, options: typing.Iterable[str]) -> str:
    """``value`` if it is one of ``options``, else ValueError naming ``name``."""
    options = tuple(options)
    if value not in options:
        raise ValueError(f"{name} must be one of {', '.join(options)}, got {value!r}")
    return value


def plain(value: Any) -> Any:
    """An OmegaConf container (or anything) as plain dicts, lists and scalars."""
    if hasattr(value, "_metadata"):  # DictConfig / ListConfig without importing omegaconf
        from omegaconf import OmegaConf

        return OmegaConf.to_container(value, resolve=True)
    return value


def build[T](cls: type[T], mapping: Mapping | None, prefix: str) -> T:
    """The dataclass ``cls`` from ``mapping``; ValueError naming ``prefix.key`` on bad input.

    Keys missing from ``mapping`` take the field's default. Fields whose type is itself a
    dataclass are built recursively from sub-mappings.
    """
    mapping = plain(mapping) if mapping is not None else {}
    if not isinstance(mapping, Mapping):
        raise ValueError(f"{prefix} must be a mapping, got {mapping!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise ValueError(
            f"{prefix}.{unknown[0]} is not a setting of {prefix} (settings: {', '.join(fields)})"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in mapping.items():
        kind = hints[name]
        if dataclasses.is_dataclass(kind):
            value = build(kind, value, f"{prefix}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    missing = [
        n
        for n, f in fields.items()
        if n not in kwargs
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ValueError(f"{prefix}.{missing[0]} is required")
    try:
        return cls(**kwargs)
    except ValueError as error:
        raise ValueError(f"{prefix}.{error}") from None
