"""What the benchmarks share: a figure checked against its target."""

from __future__ import annotations

from typing import Any


def check_target(targets: dict[str, tuple[str, float]], key: str, value: Any) -> bool | None:
    """Whether ``value`` meets ``targets[key]`` (``(">=" | "<=" | "<", bound)``); None when
    the key has no target or the figure was not measured."""
    if key not in targets or value is None:
        return None
    op, bound = targets[key]
    return bool(value >= bound if op == ">=" else value <= bound if op == "<=" else value < bound)
