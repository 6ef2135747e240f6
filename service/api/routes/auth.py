"""/auth (login, logout, who am I), /users and /tokens (admins)."""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from starlette.concurrency import run_in_threadpool

from ... import auth
from ...access import require_admin
from ...errors import Forbidden
from ...models import utcnow
from ...schemas import (LoginRequest, Me, TokenCreate, TokenCreated, TokenPublic, UserCreate,
                        UserPublic, UserUpdate)
from ..auth import (PROTECTED, SESSION_COOKIE, ActorDep, clear_login_cookies, same_origin,
                    set_login_cookies)
from ..deps import FarmDep
from ..errors import responses

router = APIRouter(tags=["auth"])  # /auth/login is public; the rest carries its dependency
_401 = responses(401)
_ADMIN = responses(401, 403)  # not an admin


@router.post("/auth/login", response_model=Me, responses=responses(401, 403))
async def login(body: LoginRequest, request: Request, response: Response, farm: FarmDep) -> Me:
    """Trade an API token for the dashboard's session cookie (HttpOnly,
    SameSite=Strict) and its CSRF cookie; 401 for a bad token."""
    if not same_origin(request):
        raise Forbidden("log in from the dashboard's own origin")

    def trade():
        with farm.sessions.begin() as session:
            return auth.create_session(session, body.token, utcnow(), farm.settings.session_hours)

    actor, session_secret = await run_in_threadpool(trade)
    set_login_cookies(response, request, session_secret, int(farm.settings.session_hours * 3600))
    return Me(user=actor.user, role=actor.role, via="cookie", token_id=actor.token_id)


@router.post("/auth/logout", status_code=status.HTTP_204_NO_CONTENT, dependencies=PROTECTED,
             responses=responses(401, 403))
def logout(request: Request, actor: ActorDep, farm: FarmDep) -> Response:
    """End this dashboard login (its session is revoked) and clear its cookies."""
    secret = request.cookies.get(SESSION_COOKIE)
    if actor.via == "cookie" and secret:
        with farm.sessions.begin() as session:
            found = session.scalars(auth.select_token_by_secret(secret)).first()
            if found is not None:
                auth.revoke_token(session, found.id, utcnow())
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    clear_login_cookies(response)
    return response


@router.get("/auth/me", response_model=Me, dependencies=PROTECTED, responses=_401)
def me(actor: ActorDep) -> Me:
    """Who the caller is: user, role, and how it authenticated."""
    return Me(user=actor.user, role=actor.role, via=actor.via, token_id=actor.token_id)


admin = APIRouter(tags=["users"], dependencies=PROTECTED, responses=_ADMIN)


@admin.get("/users", response_model=list[UserPublic])
def list_users(actor: ActorDep, farm: FarmDep) -> list[UserPublic]:
    """Every user (admins only)."""
    require_admin(actor)
    with farm.sessions() as session:
        return [UserPublic.from_user(u) for u in auth.list_users(session)]


@admin.post("/users", response_model=UserPublic, status_code=status.HTTP_201_CREATED,
            responses=responses(409, 422))  # 409: the user exists
def add_user(body: UserCreate, actor: ActorDep, farm: FarmDep) -> UserPublic:
    """Add a user with a role (admins only); then give it a token (POST /tokens)."""
    require_admin(actor)
    with farm.sessions.begin() as session:
        return UserPublic.from_user(auth.add_user(session, body.name, body.role, utcnow(),
                                                  share=float(body.share)))


@admin.patch("/users/{name}", response_model=UserPublic, responses=responses(404, 409, 422))
def update_user(name: str, body: UserUpdate, actor: ActorDep, farm: FarmDep) -> UserPublic:
    """Change a user's role, fair share or disabled flag (admins only). 409: the
    last enabled admin cannot be disabled or demoted."""
    require_admin(actor)
    with farm.sessions.begin() as session:
        return UserPublic.from_user(auth.set_user(
            session, name, role=body.role, disabled=body.disabled,
            share=None if body.share is None else float(body.share)))


@admin.get("/tokens", response_model=list[TokenPublic])
def list_tokens(actor: ActorDep, farm: FarmDep,
                user: Annotated[str | None, Query(max_length=64)] = None) -> list[TokenPublic]:
    """API tokens (never their secrets), of one user or all (admins only)."""
    require_admin(actor)
    with farm.sessions() as session:
        return [TokenPublic.from_token(t) for t in auth.list_tokens(session, user)]


@admin.post("/tokens", response_model=TokenCreated, status_code=status.HTTP_201_CREATED,
            responses=responses(404, 422))  # 404: no such user
def create_token(body: TokenCreate, actor: ActorDep, farm: FarmDep) -> TokenCreated:
    """A new token for a user (admins only); its secret is in this answer only."""
    require_admin(actor)
    now = utcnow()
    expires = None if body.expires_in_days is None else now + timedelta(days=body.expires_in_days)
    with farm.sessions.begin() as session:
        token, secret = auth.create_token(session, body.user, now, label=body.label,
                                          expires=expires)
        return TokenCreated(**TokenPublic.from_token(token).model_dump(), token=secret)


@admin.delete("/tokens/{token_id}", status_code=status.HTTP_204_NO_CONTENT,
              responses=responses(404))  # no such token
def revoke_token(token_id: str, actor: ActorDep, farm: FarmDep) -> Response:
    """Revoke a token and the dashboard logins made with it (admins only)."""
    require_admin(actor)
    with farm.sessions.begin() as session:
        auth.revoke_token(session, token_id, utcnow())
    return Response(status_code=status.HTTP_204_NO_CONTENT)
