"""Domain errors -> HTTP, in this one place.

    NotFound (ResultNotReady)            404 {"detail": "..."}
    Conflict (IllegalTransition)         409 {"detail": "..."}
    InvalidRequest, SpecError, SceneError 422 {"detail": [{"loc", "msg", "type"}]}
    TooLarge                             413 {"detail": "..."}

422 bodies have FastAPI's own validation shape, so clients parse one format;
`msg` starts with the field's name (for scenes, the location inside it).
"""

from __future__ import annotations

import re

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from renderer import SceneError, SpecError

from ..errors import Conflict, InvalidRequest, NotFound, ServiceError, TooLarge

__all__ = ["install_error_handlers", "status_of"]

_STATUS: tuple[tuple[type[Exception], int], ...] = (
    (NotFound, 404),
    (Conflict, 409),
    (InvalidRequest, 422),
    (SpecError, 422),
    (SceneError, 422),
    (TooLarge, 413),
)


def status_of(exc: Exception) -> int:
    for cls, status in _STATUS:
        if isinstance(exc, cls):
            return status
    return 500


def _invalid(loc: list, msg: str) -> list[dict]:
    return [{"loc": loc, "msg": msg, "type": "value_error"}]


def _field_loc(field: str) -> list:
    """``files[2].name`` -> ["files", 2, "name"] (FastAPI's loc for list items)."""
    return [int(part) if part.isdigit() else part
            for part in re.split(r"[.\[\]]+", field) if part]


def _body(exc: Exception) -> dict:
    if isinstance(exc, (InvalidRequest, SpecError)):
        where = getattr(exc, "source", "body")
        return {"detail": _invalid([where, *_field_loc(exc.field)], f"{exc.field}: {exc.message}")}
    if isinstance(exc, SceneError):
        loc = ["body", "scene", *([exc.location] if exc.location else [])]
        where = f"scene.{exc.location}" if exc.location else "scene"
        return {"detail": _invalid(loc, f"{where}: {exc.message}")}
    return {"detail": str(exc)}


async def _handle(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse(status_code=status_of(exc), content=_body(exc))


def install_error_handlers(app: FastAPI) -> None:
    for cls in (ServiceError, SpecError, SceneError):
        app.add_exception_handler(cls, _handle)
