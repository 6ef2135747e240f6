"""Who is calling: the request dependency every protected route has, and the
browser-safety rules that go with cookies.

    ActorDep      Annotated[Principal, Depends(current_actor)]
    PROTECTED     [Depends(current_actor)]: put on every router but the public ones
    Authenticate  ASGI middleware: the caller of a request with a body is known
                  before a byte of it is read (service.main installs it)

A request authenticates with `Authorization: Bearer <token>` (scripts, the
CLI, the Python client) or with the dashboard's session cookie. A cookie
rides along on requests the user did not mean to make (CSRF), so a request
authenticated by cookie that changes something must also carry the
`X-CSRF-Token` header equal to the `rayfarm_csrf` cookie (double submit: a
page of another origin can neither read that cookie nor set that header
without a CORS preflight we refuse), and an `Origin` header, when present,
must be this service's own. Both cookies are SameSite=Strict, so another
site's request carries neither in the first place.

FastAPI reads and parses a request's body before it solves any dependency, so
`current_actor` alone would come after a stranger's 2 GiB were read. The
`Authenticate` middleware runs it first for every request that carries a
body, but to the one route that takes a stranger's (POST /auth/login, whose
body limit is small): a caller without a valid token gets its 401 with the
body unread and the connection closed. The dependency then finds the caller
on the request.

Authentication only reads the ledger. A token's `last_used` is written on the
side, at most once a minute, and a failed write (a full disk, a read-only
ledger) is logged and forgotten for a while: it never fails the request.
"""

from __future__ import annotations

import logging
import secrets
import time
from typing import Annotated

from fastapi import Depends, Request, Response
from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from .. import auth
from ..access import Principal
from ..errors import Forbidden, ServiceError, Unauthorized
from ..farm import Farm
from ..models import utcnow
from .deps import FarmDep
from .errors import error_response

__all__ = ["ActorDep", "PROTECTED", "SESSION_COOKIE", "CSRF_COOKIE", "CSRF_HEADER",
           "Authenticate", "authenticate", "current_actor", "set_login_cookies",
           "clear_login_cookies", "same_origin"]

log = logging.getLogger(__name__)

SESSION_COOKIE = "rayfarm_session"
CSRF_COOKIE = "rayfarm_csrf"
CSRF_HEADER = "x-csrf-token"
_SAFE_METHODS = ("GET", "HEAD", "OPTIONS")


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization")
    if header is None:
        return None
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        raise Unauthorized("the Authorization header must be 'Bearer <token>'")
    return value.strip()


def same_origin(request: Request) -> bool:
    """Does the request's Origin (if any) name this service itself?"""
    origin = request.headers.get("origin")
    if origin is None:
        return True
    host = request.headers.get("host", "")
    return origin in (f"http://{host}", f"https://{host}")


def _check_csrf(request: Request) -> None:
    if request.method in _SAFE_METHODS:
        return
    if not same_origin(request):
        raise Forbidden(f"cross-origin request from {request.headers.get('origin')!r} refused")
    cookie = request.cookies.get(CSRF_COOKIE, "")
    header = request.headers.get(CSRF_HEADER, "")
    if not cookie or not header or not secrets.compare_digest(cookie, header):
        raise Forbidden("a request authenticated by the dashboard's cookie must send the "
                        f"{CSRF_HEADER} header (the {CSRF_COOKIE} cookie's value)")


LAST_USED_PAUSE = 30.0  # seconds without last_used writes after one failed


class _LastUsed:
    """When a token's last_used may be written: not for a while after a write failed."""

    failed_at: float | None = None

    def may_write(self) -> bool:
        return self.failed_at is None or time.monotonic() - self.failed_at > LAST_USED_PAUSE

    def failed(self, exc: Exception) -> None:
        if self.may_write():  # once per pause, not once per request
            log.warning("could not record a token's last use (%s: %s); requests go on",
                        type(exc).__name__, str(exc).splitlines()[0] if str(exc) else "")
        self.failed_at = time.monotonic()


_last_used = _LastUsed()


def _verify(farm: Farm, secret: str, via: str) -> Principal:
    with farm.sessions() as session:
        actor = auth.verify(session, secret, utcnow(), via=via,
                            kind="session" if via == "cookie" else "api")
        if session.dirty and _last_used.may_write():  # verify set the token's last_used
            try:
                session.commit()
            except SQLAlchemyError as exc:
                session.rollback()
                _last_used.failed(exc)
    return actor


async def authenticate(request: Request, farm: Farm) -> Principal:
    """The caller, from its bearer token or session cookie (`Unauthorized`
    without one, `Forbidden` for a cookie's change without its CSRF header);
    remembered on the request."""
    cached = getattr(request.state, "actor", None)
    if cached is not None:
        return cached
    secret = _bearer(request)
    via = "bearer"
    if secret is None:
        secret, via = request.cookies.get(SESSION_COOKIE), "cookie"
        if via == "cookie" and secret:
            _check_csrf(request)
    actor = await run_in_threadpool(_verify, farm, secret or "", via)
    request.state.actor = actor
    return actor


async def current_actor(request: Request, farm: FarmDep) -> Principal:
    """The caller, from its bearer token or session cookie; 401 without one."""
    return await authenticate(request, farm)


ActorDep = Annotated[Principal, Depends(current_actor)]
PROTECTED = [Depends(current_actor)]


# The one route that takes a body from a caller without a token: logging in.
STRANGERS_MAY_POST = frozenset({("POST", "/auth/login")})


def _has_body(scope) -> bool:
    for name, value in scope.get("headers", ()):
        if name == b"transfer-encoding" or (name == b"content-length" and value.strip() != b"0"):
            return True
    return False


class Authenticate:
    """Pure ASGI middleware: a request that carries a body is authenticated
    before the app reads a byte of it, unless its route takes a stranger's
    body (`STRANGERS_MAY_POST`), whatever the route: a body sent to a public
    page, or to a path that does not exist, needs a token too, so no path is
    a way around this. A request without a body is authenticated by its
    route's dependency, as before (or not at all, on a public route)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if (scope["type"] != "http" or not _has_body(scope)
                or (scope["method"], scope["path"].rstrip("/")) in STRANGERS_MAY_POST):
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        try:
            await authenticate(request, request.app.state.farm)
        except ServiceError as exc:
            response = error_response(exc)
            response.headers["connection"] = "close"  # the body stays unread
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)


def set_login_cookies(response: Response, request: Request, session_secret: str,
                      max_age: int) -> None:
    secure = request.url.scheme == "https"
    response.set_cookie(SESSION_COOKIE, session_secret, max_age=max_age, path="/",
                        httponly=True, samesite="strict", secure=secure)
    # Readable by the dashboard's script (it echoes it in X-CSRF-Token), by no one else.
    response.set_cookie(CSRF_COOKIE, secrets.token_urlsafe(24), max_age=max_age, path="/",
                        httponly=False, samesite="strict", secure=secure)


def clear_login_cookies(response: Response) -> None:
    for name in (SESSION_COOKIE, CSRF_COOKIE):
        response.delete_cookie(name, path="/", samesite="strict")
