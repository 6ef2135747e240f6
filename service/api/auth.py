"""Who is calling: the request dependency every protected route has, and the
browser-safety rules that go with cookies.

    ActorDep      Annotated[Principal, Depends(current_actor)]
    PROTECTED     [Depends(current_actor)]: put on every router but the public ones

A request authenticates with `Authorization: Bearer <token>` (scripts, the
CLI, the Python client) or with the dashboard's session cookie. A cookie
rides along on requests the user did not mean to make (CSRF), so a request
authenticated by cookie that changes something must also carry the
`X-CSRF-Token` header equal to the `rayfarm_csrf` cookie (double submit: a
page of another origin can neither read that cookie nor set that header
without a CORS preflight we refuse), and an `Origin` header, when present,
must be this service's own. Both cookies are SameSite=Strict, so another
site's request carries neither in the first place.
"""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, Request, Response
from starlette.concurrency import run_in_threadpool

from .. import auth
from ..access import Principal
from ..errors import Forbidden, Unauthorized
from ..models import utcnow
from .deps import FarmDep

__all__ = ["ActorDep", "PROTECTED", "SESSION_COOKIE", "CSRF_COOKIE", "CSRF_HEADER",
           "current_actor", "set_login_cookies", "clear_login_cookies", "same_origin"]

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


async def current_actor(request: Request, farm: FarmDep) -> Principal:
    """The caller, from its bearer token or session cookie; 401 without one."""
    cached = getattr(request.state, "actor", None)
    if cached is not None:
        return cached
    secret = _bearer(request)
    via = "bearer"
    if secret is None:
        secret, via = request.cookies.get(SESSION_COOKIE), "cookie"
        if via == "cookie" and secret:
            _check_csrf(request)

    def check() -> Principal:
        with farm.sessions.begin() as session:  # commits the token's last_used
            return auth.verify(session, secret or "", utcnow(), via=via,
                               kind="session" if via == "cookie" else "api")

    actor = await run_in_threadpool(check)
    request.state.actor = actor
    return actor


ActorDep = Annotated[Principal, Depends(current_actor)]
PROTECTED = [Depends(current_actor)]


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
