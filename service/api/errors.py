"""Domain errors -> HTTP, in this one place.

    Unauthorized                         401 {"detail": "..."} + WWW-Authenticate: Bearer
    Forbidden                            403 {"detail": "..."}
    RateLimited                          429 {"detail": "..."} + Retry-After
    NotFound (ResultNotReady)            404 {"detail": "..."}
    Conflict (IllegalTransition)         409 {"detail": "..."}
    InvalidRequest, SpecError, SceneError 422 {"detail": [{"loc", "msg", "type"}]}
    RequestValidationError (FastAPI)     422 {"detail": [{"loc", "msg", "type", "input", ...}]}
    TooLarge                             413 {"detail": "..."}
    InsufficientStorage                  507 {"detail": "..."} + Retry-After
    OperationalError of a ledger that is full (or read-only)   507 the same way

422 bodies have FastAPI's own validation shape, so clients parse one format;
`msg` starts with the field's name (for scenes, the location inside it).
FastAPI's own 422s echo the offending `input`: a NaN or infinity there (Python
reads them in JSON bodies) is replaced by its repr, and a lone surrogate by
its escape, since no JSON writer may send either back (a body holding one is
refused before validation anyway: service.api.deps.unicode_body). A JSON body that cannot even be decoded (not UTF-8, nested too
deeply) is FastAPI's bare 400; here it is the 422 of any other invalid JSON.

`responses(401, 404, ...)` documents these answers on a route (`responses=`
of FastAPI), so the OpenAPI schema lists every status a route can give.
"""

from __future__ import annotations

import math
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm.exc import StaleDataError
from starlette.exceptions import HTTPException

from renderer import SceneError, SpecError

from ..disk import RETRY_AFTER, ledger_cannot_write
from ..errors import (Conflict, Forbidden, InsufficientStorage, InvalidRequest, NotFound,
                      RateLimited, ServiceError, TooLarge, Unauthorized)

__all__ = ["install_error_handlers", "status_of", "error_response", "responses", "Message",
           "Invalid"]

_STATUS: tuple[tuple[type[Exception], int], ...] = (
    (Unauthorized, 401),
    (Forbidden, 403),
    (RateLimited, 429),
    (NotFound, 404),
    (Conflict, 409),
    (InvalidRequest, 422),
    (SpecError, 422),
    (SceneError, 422),
    (TooLarge, 413),
    (InsufficientStorage, 507),
    # A write based on a read the scheduler made stale meanwhile (optimistic
    # locking, service.models). Routes that change jobs try again
    # (jobs.retrying); this is the net under any that does not: a conflict to
    # try again, never a 500.
    (StaleDataError, 409),
)


def status_of(exc: Exception) -> int:
    for cls, status in _STATUS:
        if isinstance(exc, cls):
            return status
    return 500


def _invalid(loc: list, msg: str) -> list[dict]:
    return [{"loc": loc, "msg": msg, "type": "value_error"}]


def _field_loc(field: str) -> list:
    """``files[2].name`` -> ["files", 2, "name"] (FastAPI's loc for list items).
    Field names can be a client's (an unknown form field): ASCII digits only,
    since str.isdigit() also takes '¹', which int() refuses."""
    return [int(part) if part.isascii() and part.isdigit() else part
            for part in re.split(r"[.\[\]]+", field) if part]


def _body(exc: Exception) -> dict:
    if isinstance(exc, (InvalidRequest, SpecError)):
        where = getattr(exc, "source", "body")
        return {"detail": _invalid([where, *_field_loc(exc.field)], f"{exc.field}: {exc.message}")}
    if isinstance(exc, SceneError):
        loc = ["body", "scene", *([exc.location] if exc.location else [])]
        where = f"scene.{exc.location}" if exc.location else "scene"
        return {"detail": _invalid(loc, f"{where}: {exc.message}")}
    if isinstance(exc, StaleDataError):
        return {"detail": "the farm changed this meanwhile; try again"}
    return {"detail": str(exc)}


def _headers(exc: Exception) -> dict[str, str] | None:
    if isinstance(exc, Unauthorized):
        return {"WWW-Authenticate": 'Bearer realm="rayfarm"'}
    if isinstance(exc, (RateLimited, InsufficientStorage)):
        return {"Retry-After": str(max(1, math.ceil(exc.retry_after)))}
    return None


def error_response(exc: Exception) -> JSONResponse:
    """The answer to a domain error, as the handlers give it (for middleware,
    which runs outside them)."""
    return JSONResponse(status_code=status_of(exc), content=_body(exc), headers=_headers(exc))


async def _handle(request: Request, exc: Exception) -> JSONResponse:
    return error_response(exc)


_SOURCES = ("body", "query", "path", "header", "cookie")


_ECHO_DEPTH = 8  # levels of an error's echoed input shown; a body may nest far deeper


def _json_safe(value: Any, depth: int = 0) -> Any:
    """`value` with every non-finite float replaced by its repr, a lone
    surrogate in a string by its escape, and what lies deeper than
    _ECHO_DEPTH by "..."."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, (dict, list, tuple)) and depth >= _ECHO_DEPTH:
        return "..."
    if isinstance(value, dict):
        return {_json_safe(key): _json_safe(item, depth + 1) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(item, depth + 1) for item in value]
    return value


def _field_name(loc: list) -> str:
    """["body", "options", "radius"] -> "options.radius"; ["body", "files", 2] -> "files[2]"."""
    parts = loc[1:] if loc and loc[0] in _SOURCES and len(loc) > 1 else loc
    name = ""
    for part in parts:
        name += f"[{part}]" if isinstance(part, int) else (f".{part}" if name else str(part))
    return name


def _named(error: dict) -> dict:
    """A FastAPI validation error whose msg starts with the field's name."""
    error = dict(error)
    loc = list(error.get("loc", ()))
    raw = error.get("input")
    if error.get("type") == "json_invalid":
        where = loc[1] if len(loc) > 1 else "?"
        reason = (error.get("ctx") or {}).get("error", "")
        error["msg"] = f"body: invalid JSON at character {where}: {reason}".rstrip(": ")
    else:
        error["msg"] = f"{_field_name(loc)}: {error.get('msg', '')}"
        if isinstance(raw, float) and not math.isfinite(raw):
            error["msg"] += f", got {raw!r}"
    return jsonable_encoder(_json_safe(error))


async def _invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
    return JSONResponse(status_code=422, content={"detail": [_named(e) for e in exc.errors()]})


_UNPARSABLE = "There was an error parsing the body"  # FastAPI's words for a body it cannot decode


async def _http_error(request: Request, exc: HTTPException) -> Response:
    cause = exc.__cause__
    if exc.status_code == 400 and cause is not None and exc.detail == _UNPARSABLE:
        msg = f"body: invalid JSON ({type(cause).__name__}: {cause})"[:300]
        return JSONResponse(status_code=422, content={"detail": [
            {"loc": ["body"], "msg": msg, "type": "json_invalid"}]})
    return await http_exception_handler(request, exc)


async def _ledger_error(request: Request, exc: OperationalError) -> JSONResponse:
    """A write the ledger refused for want of room is a 507 to try again
    later (service.disk); any other database error stays a 500."""
    reason = ledger_cannot_write(exc)
    if reason is None:
        raise exc
    return error_response(InsufficientStorage(
        f"no room: {reason}; nothing was changed, what is stored is kept and served, try "
        "again when there is room",
        retry_after=RETRY_AFTER))


def install_error_handlers(app: FastAPI) -> None:
    for cls in (ServiceError, SpecError, SceneError, StaleDataError):
        app.add_exception_handler(cls, _handle)
    app.add_exception_handler(OperationalError, _ledger_error)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.add_exception_handler(HTTPException, _http_error)


# -- the same answers, as the OpenAPI schema documents them ----------------------------

class Message(BaseModel):
    """An error that is no field's: `{"detail": "..."}`."""

    detail: str


class InvalidField(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class Invalid(BaseModel):
    """An invalid request: FastAPI's validation shape, `msg` naming the field."""

    detail: list[InvalidField]


_DOCUMENTED: dict[int, tuple[type[BaseModel], str]] = {
    401: (Message, "no valid token (Authorization: Bearer, or the dashboard's session cookie)"),
    403: (Message, "the caller's role may not do this (viewers only read), or a request "
                   "authenticated by cookie without its CSRF header"),
    404: (Message, "no such resource, or not the caller's to see"),
    409: (Message, "the request contradicts the resource's state"),
    413: (Message, "the request body (or its number of files) is above its limit"),
    422: (Invalid, "an invalid field: loc and msg name it"),
    429: (Message, "too many requests for now: Retry-After says when to try again"),
    507: (Message, "no room for new work now (a full disk): the reason, and Retry-After"),
}


def responses(*statuses: int) -> dict[int, dict]:
    """FastAPI `responses=` documenting these error statuses on a route."""
    return {status: {"model": _DOCUMENTED[status][0], "description": _DOCUMENTED[status][1]}
            for status in statuses}
