"""/methods and /samplers: straight from the renderer's registry."""

from __future__ import annotations

from fastapi import APIRouter

from renderer import METHODS, SAMPLERS, RenderSpec

router = APIRouter(tags=["registry"])


@router.get("/methods")
def list_methods() -> list[dict]:
    """Rendering methods with their options (name, type, default, choices)."""
    return [m.describe() for m in dict.fromkeys(METHODS.values())]  # aliases once


@router.get("/samplers")
def list_samplers() -> list[dict]:
    """Pixel samplers; `default` marks the one a job gets without naming one."""
    default = RenderSpec().sampler
    return [{**s.describe(), "default": s.name == default} for s in SAMPLERS.values()]
