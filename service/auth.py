"""Users and their tokens: create, verify, revoke, and the first admin. Plain
Python on the ledger, no HTTP (the routes are in service/api/routes/auth.py,
the request dependency in service/api/auth.py).

    user = add_user(session, "ana", "artist", now=utcnow())
    token, secret = create_token(session, "ana", now=utcnow(), label="laptop")
    actor = verify(session, secret, now=utcnow())        # Principal("ana", "artist", ...)

A token's secret is 256 random bits (`rf_` + base64url), shown once; the ledger
keeps only its SHA-256. That is enough for a secret of this entropy: a slow
password hash protects guessable passwords, not random keys, and the
lookup by hash needs no comparison in Python (no timing side channel on the
secret). A dashboard login ("session") is a token of its own, made from the
token pasted at login; revoking that token ends its sessions too.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import secrets
from datetime import datetime, timedelta
from pathlib import Path

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from .access import ROLES, Principal
from .errors import Conflict, InvalidRequest, NotFound, Unauthorized
from .models import ApiToken, User, utcnow

__all__ = ["TOKEN_PREFIX", "hash_secret", "add_user", "list_users", "set_user", "create_token",
           "list_tokens", "revoke_token", "verify", "create_session", "bootstrap_admin",
           "admin_token_path", "select_token_by_secret", "still_valid", "logins_mark",
           "USER_NAME"]

log = logging.getLogger(__name__)

TOKEN_PREFIX = "rf_"
USER_NAME = re.compile(r"[a-z0-9][a-z0-9._-]{0,63}")
LAST_USED_EVERY = timedelta(minutes=1)  # a token's last_used is written at most this often
ADMIN_TOKEN_FILE = "admin.token"


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8", "surrogatepass")).hexdigest()


def _new_secret() -> str:
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


# -- users ----------------------------------------------------------------------------

def _check_role(role: str) -> str:
    if role not in ROLES:
        raise InvalidRequest("role", f"unknown role '{role}' (allowed: {', '.join(ROLES)})")
    return role


def add_user(session: Session, name: str, role: str, now: datetime, share: float = 1.0) -> User:
    """A new user (names: lower-case letters, digits, '.', '_', '-'; at most 64)."""
    if not isinstance(name, str) or not USER_NAME.fullmatch(name):
        raise InvalidRequest("name", f"invalid user name {name!r}: 1 to 64 of a-z, 0-9, "
                                     "'.', '_', '-', starting with a letter or digit")
    _check_role(role)
    _check_share(share)
    if session.get(User, name) is not None:
        raise Conflict(f"user '{name}' exists already")
    user = User(name=name, role=role, share=float(share), created=now, disabled=False)
    session.add(user)
    session.flush()
    return user


def _check_share(share: float) -> None:
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.01 <= share <= 1000:
        raise InvalidRequest("share", f"must be a number between 0.01 and 1000, got {share!r}")


def list_users(session: Session) -> list[User]:
    return list(session.scalars(select(User).order_by(User.name)))


def get_user(session: Session, name: str) -> User:
    user = session.get(User, name)
    if user is None:
        raise NotFound(f"no user '{name}'")
    return user


def set_user(session: Session, name: str, *, role: str | None = None, share: float | None = None,
             disabled: bool | None = None) -> User:
    """Change a user's role, fair share or disabled flag (a disabled user's tokens stop working).

    The last enabled admin may be neither disabled nor demoted (`Conflict`):
    nobody could manage users any more, the token-less CLI excepted."""
    user = get_user(session, name)
    if role is not None:
        _check_role(role)
    leaves = user.role == "admin" and not user.disabled and (
        (role is not None and role != "admin") or bool(disabled))
    if leaves and _last_admin(session, name):
        what = "disabled" if disabled else f"made {role}"
        raise Conflict(f"user '{name}' is the last enabled admin and cannot be {what}: make "
                       "another user admin first")
    if role is not None:
        user.role = _check_role(role)
    if share is not None:
        _check_share(share)
        user.share = float(share)
    if disabled is not None:
        user.disabled = bool(disabled)
    return user


def _last_admin(session: Session, name: str) -> bool:
    """True if no enabled admin but `name` exists. The others' rows are locked
    until the transaction ends (PostgreSQL; SQLite has one writer at a time),
    so two admins disabling each other at once cannot both succeed."""
    return session.scalars(select(User.name).where(
        User.role == "admin", User.disabled.is_(False), User.name != name)
        .with_for_update()).first() is None


# -- tokens ---------------------------------------------------------------------------

def create_token(session: Session, user: str, now: datetime, *, label: str = "",
                 expires: datetime | None = None, secret: str | None = None,
                 kind: str = "api", parent: str | None = None) -> tuple[ApiToken, str]:
    """A new token for `user`: (its row, its secret). The secret is never stored."""
    get_user(session, user)
    if expires is not None and expires <= now:
        raise InvalidRequest("expires", "must lie in the future")
    secret = secret or _new_secret()
    token = ApiToken(id=secrets.token_hex(8), user=user, kind=kind, parent=parent,
                     secret_hash=hash_secret(secret), label=(label or "")[:200], created=now,
                     expires=expires, revoked=None, last_used=None)
    session.add(token)
    session.flush()
    return token, secret


def list_tokens(session: Session, user: str | None = None, *, kind: str = "api") -> list[ApiToken]:
    query = select(ApiToken).where(ApiToken.kind == kind).order_by(ApiToken.created, ApiToken.id)
    if user is not None:
        query = query.where(ApiToken.user == user)
    return list(session.scalars(query))


def revoke_token(session: Session, token_id: str, now: datetime, *,
                 user: str | None = None) -> ApiToken:
    """Revoke a token (and the dashboard sessions made from it). With `user`,
    only that user's token is found (someone else's: NotFound)."""
    token = session.get(ApiToken, token_id)
    if token is None or (user is not None and token.user != user):
        raise NotFound(f"no token '{token_id}'")
    if token.revoked is None:
        token.revoked = now
    session.execute(update(ApiToken).where(ApiToken.parent == token.id,
                                           ApiToken.revoked.is_(None)).values(revoked=now))
    return token


def select_token_by_secret(secret: str):
    """The SELECT of the token row whose secret is `secret`."""
    return select(ApiToken).where(ApiToken.secret_hash == hash_secret(secret))


def _usable(token: ApiToken | None, now: datetime) -> bool:
    return (token is not None and token.revoked is None
            and (token.expires is None or token.expires > now))


def verify(session: Session, secret: str, now: datetime, via: str = "bearer",
           kind: str | None = None) -> Principal:
    """The principal a secret stands for; `Unauthorized` for a missing, unknown,
    expired or revoked token, a disabled user, or a session whose token was revoked."""
    if not secret or not isinstance(secret, str) or len(secret) > 200:
        raise Unauthorized("a token is required: Authorization: Bearer <token> "
                           "(rayfarm tokens create USER; the service printed the admin's "
                           "login URL when it started)")
    token = session.scalars(select_token_by_secret(secret)).first()
    if token is not None and kind is not None and token.kind != kind:
        token = None
    if not _usable(token, now):
        raise Unauthorized("invalid, expired or revoked token")
    if token.parent is not None and not _usable(session.get(ApiToken, token.parent), now):
        raise Unauthorized("this login's token was revoked or expired; log in again")
    user = session.get(User, token.user)
    if user is None or user.disabled:
        raise Unauthorized(f"user '{token.user}' is disabled")
    if token.last_used is None or now - token.last_used > LAST_USED_EVERY:
        token.last_used = now  # written with the caller's transaction
    return Principal(user.name, user.role, token_id=token.parent or token.id, via=via,
                     session_id=token.id if token.parent else None)


def still_valid(session: Session, actor: Principal, now: datetime) -> bool:
    """Is the token `actor` authenticated with (and its dashboard login, if it
    came with one) still usable, and its user enabled with the same role? (A
    long-lived event stream asks whenever `logins_mark` moved: a logout, a
    revoked token, a disabled user or a new role ends it.)"""
    if actor.token_id is None:
        return True
    user = session.get(User, actor.user)
    return (_usable(session.get(ApiToken, actor.token_id), now) and user is not None
            and not user.disabled and user.role == actor.role
            and (actor.session_id is None
                 or _usable(session.get(ApiToken, actor.session_id), now)))


def logins_mark(session: Session) -> tuple:
    """A value that changes whenever a login may have ended early: the number
    of revoked tokens (a revocation is never undone; a logout revokes its
    session) and every user's role and disabled flag. Two small reads."""
    revoked = session.scalar(select(func.count()).select_from(ApiToken)
                             .where(ApiToken.revoked.is_not(None)))
    users = tuple(session.execute(select(User.name, User.role, User.disabled)
                                  .order_by(User.name)).all())
    return revoked, users


def create_session(session: Session, secret: str, now: datetime,
                   hours: float) -> tuple[Principal, str]:
    """Trade an API token for a dashboard session: (principal, session secret)."""
    actor = verify(session, secret, now, kind="api")
    _, session_secret = create_token(session, actor.user, now, kind="session",
                                     parent=actor.token_id, label="dashboard login",
                                     expires=now + timedelta(hours=hours))
    return actor, session_secret


# -- the first admin ------------------------------------------------------------------------

def admin_token_path(data_dir: Path) -> Path:
    return Path(data_dir) / ADMIN_TOKEN_FILE


def _write_private(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text + "\n")
    os.chmod(path, 0o600)


def bootstrap_admin(sessions: sessionmaker[Session], data_dir: Path,
                    admin_token: str = "") -> str | None:
    """Make sure the farm has an admin; return a login secret for it, or None.

    With no admin in the ledger: create user `admin` and a token (`admin_token`
    if given, else a random one) and keep its secret in `<data_dir>/admin.token`
    (mode 0600, as Jupyter keeps its server tokens in runtime files) so the
    service can print the login URL and the CLI on this machine can read it.
    Later starts return the secret in that file while it is still valid."""
    path = admin_token_path(data_dir)
    now = utcnow()
    if admin_token and len(admin_token) < 32:
        raise ValueError("RAYFARM_ADMIN_TOKEN must be at least 32 characters")
    with sessions() as session:
        has_admin = session.scalars(select(User.name).where(User.role == "admin",
                                                            User.disabled.is_(False))).first()
    if has_admin is None:
        try:
            with sessions.begin() as session:
                if session.get(User, "admin") is None:
                    add_user(session, "admin", "admin", now)
                else:
                    set_user(session, "admin", role="admin", disabled=False)
                _, secret = create_token(session, "admin", now, label="first admin token",
                                         secret=admin_token or None)
        except IntegrityError:  # another service made it at the same moment
            pass
        else:
            _write_private(path, secret)
            log.info("created user 'admin' and its first token (%s)", path)
            return secret
    try:
        secret = path.read_text().strip()
    except OSError:
        return None
    with sessions() as session:
        token = session.scalars(select_token_by_secret(secret)).first()
        return secret if _usable(token, now) else None
