"""/scenes: the built-in scenes."""

from __future__ import annotations

from fastapi import APIRouter

from renderer import builtin_scene_names, resolve_document

from ...schemas import ScenePublic

router = APIRouter(tags=["registry"])


@router.get("/scenes", response_model=list[ScenePublic])
def list_scenes() -> list[ScenePublic]:
    """Built-in scenes a job may name (or send an inline scene document instead)."""
    out = []
    for name in builtin_scene_names():
        doc = resolve_document(name, allow_files=False)
        out.append(ScenePublic(name=name, description=doc.get("description", ""),
                               width=doc["camera"]["width"], height=doc["camera"]["height"]))
    return out
