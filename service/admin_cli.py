"""`rayfarm users` and `rayfarm tokens`: manage accounts on the ledger directly
(the machine that runs the service, with its RAYFARM_* settings); admins can
do the same over the API (`/users`, `/tokens`).

    rayfarm users add ana --role artist [--share 2]
    rayfarm users list
    rayfarm users set ana --role viewer | --share 3 | --disable | --enable
    rayfarm tokens create ana [--label laptop] [--expires-days 30]   # prints the secret once
    rayfarm tokens list [--user ana]
    rayfarm tokens revoke TOKEN_ID
    rayfarm cache info                         the renderer's disk caches: size, entries
    rayfarm cache clear                        empty them ($RAYFARM_CACHE_DIR or <data_dir>/cache)
"""

from __future__ import annotations

import argparse
import sys
from datetime import timedelta

from .access import ROLES

__all__ = ["add_admin_commands"]


def _ledger():
    from .db import open_ledger
    from .settings import Settings

    settings = Settings()
    settings.keep_files_private()  # it may create the SQLite ledger
    engine, sessions = open_ledger(settings)
    return engine, sessions


def _fail(command: str, exc: Exception) -> int:
    print(f"rayfarm {command}: {exc}", file=sys.stderr)
    return 2


def _users(args: argparse.Namespace) -> int:
    from . import auth
    from .errors import ServiceError
    from .models import utcnow

    engine, sessions = _ledger()
    try:
        with sessions.begin() as session:
            if args.action == "add":
                user = auth.add_user(session, args.name, args.role, utcnow(), share=args.share)
                print(f"added user {user.name} ({user.role}, share {user.share:g}); give it a "
                      f"token: rayfarm tokens create {user.name}")
            elif args.action == "set":
                disabled = True if args.disable else False if args.enable else None
                user = auth.set_user(session, args.name, role=args.role, share=args.share,
                                     disabled=disabled)
                print(f"{user.name}: {user.role}, share {user.share:g}"
                      f"{', disabled' if user.disabled else ''}")
            else:
                print(f"{'NAME':20} {'ROLE':8} {'SHARE':>6}  CREATED")
                for user in auth.list_users(session):
                    flag = "  (disabled)" if user.disabled else ""
                    print(f"{user.name:20} {user.role:8} {user.share:6g}  "
                          f"{user.created:%Y-%m-%d %H:%M}{flag}")
    except ServiceError as exc:
        return _fail(f"users {args.action}", exc)
    finally:
        engine.dispose()
    return 0


def _tokens(args: argparse.Namespace) -> int:
    from . import auth
    from .errors import ServiceError
    from .models import utcnow

    engine, sessions = _ledger()
    now = utcnow()
    try:
        with sessions.begin() as session:
            if args.action == "create":
                expires = now + timedelta(days=args.expires_days) if args.expires_days else None
                token, secret = auth.create_token(session, args.user, now, label=args.label,
                                                  expires=expires)
                print(f"token {token.id} for {token.user}"
                      f"{f', expires {expires:%Y-%m-%d %H:%M} UTC' if expires else ''}; "
                      "shown this once:", file=sys.stderr)
                print(secret)
            elif args.action == "revoke":
                token = auth.revoke_token(session, args.token_id, now)
                print(f"revoked token {token.id} of {token.user}")
            else:
                print(f"{'ID':16} {'USER':16} {'STATE':8} {'EXPIRES':16} {'LAST USED':16} LABEL")
                for t in auth.list_tokens(session, args.user):
                    state = ("revoked" if t.revoked else
                             "expired" if t.expires and t.expires <= now else "active")
                    when = (lambda d: f"{d:%Y-%m-%d %H:%M}" if d else "-")
                    print(f"{t.id:16} {t.user:16} {state:8} {when(t.expires):16} "
                          f"{when(t.last_used):16} {t.label}")
    except ServiceError as exc:
        return _fail(f"tokens {args.action}", exc)
    finally:
        engine.dispose()
    return 0


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def _cache(args: argparse.Namespace) -> int:
    from renderer.cache import CACHES, DiskCache

    from .settings import Settings

    settings = Settings()
    settings.keep_files_private()
    caches = [DiskCache(settings.cache_dir / name, settings.cache_max_bytes) for name in CACHES]
    if args.action == "clear":
        for cache in caches:
            removed = cache.clear()
            print(f"{cache.directory.name}: removed {removed} entries ({cache.directory})")
    else:
        for cache in caches:
            info = cache.info()
            print(f"{info.directory.name}: {info.entries} entries, {_size(info.bytes)} "
                  f"({info.bytes} bytes) of {_size(info.max_bytes)} ({info.directory})")
    return 0


def add_admin_commands(sub: argparse._SubParsersAction) -> None:
    users = sub.add_parser("users", help="manage users on the ledger (admin, this machine)")
    actions = users.add_subparsers(dest="action", required=True)
    add = actions.add_parser("add", help="add a user")
    add.add_argument("name")
    add.add_argument("--role", choices=ROLES, default="artist")
    add.add_argument("--share", type=float, default=1.0,
                     help="weight in the fair share between owners (default 1)")
    change = actions.add_parser("set", help="change a user's role, share or disabled flag")
    change.add_argument("name")
    change.add_argument("--role", choices=ROLES)
    change.add_argument("--share", type=float)
    flag = change.add_mutually_exclusive_group()
    flag.add_argument("--disable", action="store_true", help="its tokens stop working")
    flag.add_argument("--enable", action="store_true")
    actions.add_parser("list", help="list users")
    users.set_defaults(run=_users)

    tokens = sub.add_parser("tokens", help="manage API tokens on the ledger (admin, this machine)")
    actions = tokens.add_subparsers(dest="action", required=True)
    create = actions.add_parser("create", help="a new token for a user; prints its secret once")
    create.add_argument("user")
    create.add_argument("--label", default="", help="what it is for (shown by tokens list)")
    create.add_argument("--expires-days", type=float, help="expire after this many days")
    revoke = actions.add_parser("revoke", help="revoke a token (and its dashboard logins)")
    revoke.add_argument("token_id", metavar="TOKEN_ID")
    listing = actions.add_parser("list", help="list tokens (never their secrets)")
    listing.add_argument("--user")
    tokens.set_defaults(run=_tokens)

    cache = sub.add_parser("cache", help="the renderer's on-disk caches (RAYFARM_CACHE_DIR, "
                                         "default <data_dir>/cache)")
    actions = cache.add_subparsers(dest="action", required=True)
    actions.add_parser("info", help="size and entries of each cache")
    actions.add_parser("clear", help="remove every entry")
    cache.set_defaults(run=_cache)
