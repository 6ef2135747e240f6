"""Render parameters (`RenderSpec`) and their bounds: the one place they live.

The service's request validation reads `BOUNDS` and the method/sampler
registries, so the API, the CLI and the renderer refuse the same things with
the same words.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from .errors import SpecError
from .registry import METHODS, SAMPLERS

__all__ = ["RenderSpec", "BOUNDS", "DEFAULT_MAX_WORK", "default_depth"]

# (lowest, highest) accepted value of each integer parameter.
BOUNDS: dict[str, tuple[int, int]] = {
    "spp": (1, 1 << 20),
    "depth": (0, 64),
    "tile_size": (4, 4096),
    "width": (1, 8192),
    "height": (1, 8192),
    "seed": (0, (1 << 63) - 1),
}

# Pixels x spp above which a job is refused unless the caller raises the limit.
DEFAULT_MAX_WORK = 1 << 32


@dataclass(frozen=True)
class RenderSpec:
    """Everything that decides a render's pixels, apart from the scene.

    An alias names its method (`path` is `path-mis`): the spec keeps the
    method's own name, so what is stored, reported and written to an EXR says
    one method one way.

    >>> RenderSpec(method="path", spp=16, depth=5, width=256, height=256).method
    'path-mis'
    """

    method: str = "path-mis"
    spp: int = 16
    depth: int = 5
    width: int = 256
    height: int = 256
    tile_size: int = 64
    seed: int = 0
    sampler: str = "sobol"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        method = METHODS.get(self.method) if isinstance(self.method, str) else None
        if method is not None and method.name != self.method:
            object.__setattr__(self, "method", method.name)  # frozen: set once, here

    def validate(self, max_work: int = DEFAULT_MAX_WORK, scene: dict | None = None) -> "RenderSpec":
        """Check bounds and registry names (and, given the resolved `scene`
        document, what the method's options make of it); return self or raise
        `SpecError`."""
        for name, (lo, hi) in BOUNDS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise SpecError(name, f"must be an integer, got {value!r}")
            if not lo <= value <= hi:
                raise SpecError(name, f"must be between {lo} and {hi}, got {value}")
        if self.method not in METHODS:
            raise SpecError("method", f"unknown method '{self.method}' "
                                      f"(allowed: {', '.join(METHODS)})")
        if self.sampler not in SAMPLERS:
            raise SpecError("sampler", f"unknown sampler '{self.sampler}' "
                                       f"(allowed: {', '.join(SAMPLERS)})")
        METHODS[self.method].check_options(self.options)
        work = self.width * self.height * self.spp
        if work > max_work:
            raise SpecError("spp", f"total work width x height x spp = {work} exceeds the "
                                   f"limit {max_work}; lower spp or the resolution")
        if scene is not None:
            METHODS[self.method].check(self, scene)
        return self

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RenderSpec":
        return cls(**{k: v for k, v in data.items() if k in cls.__dataclass_fields__})


def default_depth(doc: dict) -> int:
    """A job's depth when its request gives none: the scene's
    `defaults.max_depth` (an imported file's integrator block), else 5."""
    defaults = doc.get("defaults") if isinstance(doc, dict) else None
    depth = defaults.get("max_depth") if isinstance(defaults, dict) else None
    return depth if isinstance(depth, int) and not isinstance(depth, bool) else RenderSpec.depth
