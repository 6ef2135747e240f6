"""/methods and /samplers: straight from the renderer's registry."""

from __future__ import annotations

from fastapi import APIRouter

from renderer import METHODS, SAMPLERS, RenderSpec
from renderer.target import supports_target

router = APIRouter(tags=["registry"])


@router.get("/methods")
def list_methods() -> list[dict]:
    """Rendering methods with their options (name, type, default, choices) and
    whether a job of theirs may give a noise `target` (renderer/target.py)."""
    return [{**m.describe(), "noise_target": supports_target(m.name)}
            for m in dict.fromkeys(METHODS.values())]  # aliases once


@router.get("/samplers")
def list_samplers() -> list[dict]:
    """Pixel samplers; `default` marks the one a job gets without naming one."""
    default = RenderSpec().sampler
    return [{**s.describe(), "default": s.name == default} for s in SAMPLERS.values()]
