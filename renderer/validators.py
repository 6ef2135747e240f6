"""Small validators of scene documents; each raises SceneError naming the
location (scene_format.py, material_format.py)."""

from __future__ import annotations

import json
import math
from typing import Any

from .errors import SceneError

MAX_COORDINATE = 1e6  # |x|, |y|, |z| of any point (local and world), transform entry, radius


def _require(obj: dict, key: str, loc: str) -> Any:
    if key not in obj:
        raise SceneError(f"missing required field '{key}'", loc)
    return obj[key]


def _number(value: Any, loc: str, *, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneError(f"expected a finite number, got {json.dumps(value)[:60]}", loc)
    v = float(value)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise SceneError(f"must be {'>' if lo_open else '>='} {lo}, got {v}", loc)
    if hi is not None and v > hi:
        raise SceneError(f"must be <= {hi}, got {v}", loc)
    return v


def _vec3(value: Any, loc: str, *, nonneg: bool = False,
          limit: float = MAX_COORDINATE) -> list[float]:
    """Three finite numbers within +-`limit` (0..limit if `nonneg`)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value, value, value]  # a scalar means grey
    if not isinstance(value, list) or len(value) != 3:
        raise SceneError("expected a list of 3 numbers", loc)
    return [_number(v, f"{loc}[{i}]", lo=0.0 if nonneg else -limit, hi=limit)
            for i, v in enumerate(value)]


def _coordinate(value: Any, loc: str, **bounds) -> float:
    """A finite number within +-MAX_COORDINATE (and `bounds`, if tighter)."""
    return _number(value, loc, **{"lo": -MAX_COORDINATE, "hi": MAX_COORDINATE, **bounds})


def _bool(value: Any, loc: str) -> bool:
    if not isinstance(value, bool):
        raise SceneError(f"expected true or false, got {json.dumps(value)[:60]}", loc)
    return value


def _name_list(allowed) -> str:
    return ", ".join(allowed)
