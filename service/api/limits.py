"""Request-body limits, as a pure ASGI middleware: 413 before a byte too many is kept.

    install_body_limits(app, settings)

Every route has a limit. Most bodies are a few hundred bytes (a login, a
user, a token, a job's change, an experiment, a job action), so every route
gets `max_body_bytes` (64 KiB) unless it is named with a larger one: POST
/scenes (uploads, `max_upload_bytes`) and POST /jobs (inline scene documents,
`max_job_bytes`). A route is named by its method and path template, as the
app declares it ("PATCH /jobs/{job_id}" covers every job), so a limit cannot
be dodged by a path parameter.

FastAPI reads and parses a body (JSON, multipart) before any dependency or
handler runs, so a check there comes after the body was spooled. This
middleware sits in front of all that:
- a Content-Length above the limit is answered 413 at once, the body unread;
- a body without one (chunked) is counted as it streams: the moment it passes
  the limit, the app's `receive` raises `BodyTooLarge` (and then reports a
  disconnect), and whatever the app answers instead is replaced by the 413.
The 413 asks the server to close the connection (the rest of the body is
never read). Who may send a body at all is decided right after this (the
`Authenticate` middleware of service.api.auth): a body is not read for a
caller without a valid token, but a login's.
"""

from __future__ import annotations

import json
from typing import Mapping, NamedTuple

from starlette.routing import compile_path

from ..settings import Settings

__all__ = ["BodyLimit", "BodyTooLarge", "Limit", "install_body_limits"]


class BodyTooLarge(Exception):
    """Raised into the app by `receive` when the body passes its limit."""


class Limit(NamedTuple):
    """The most bytes a body may have, and the setting that says so."""

    max_bytes: int
    setting: str


def _round_size(n: int) -> str:
    """``"64 MiB; "`` for a round figure, else nothing."""
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale and n % scale == 0:
            return f"{n // scale} {unit}; "
    return ""


class BodyLimit:
    """Limits every request body: `default`, or the limit of the route's
    ``(method, path template)`` in `limits`: ``{("POST", "/scenes"): Limit(...)}``."""

    def __init__(self, app, default: Limit, limits: Mapping[tuple[str, str], Limit]):
        self.app = app
        self.default = default
        self.limits = [(method, compile_path(template)[0], limit)
                       for (method, template), limit in limits.items()]

    def limit_of(self, method: str, path: str) -> Limit:
        path = path.rstrip("/") or "/"  # "/scenes/" is redirected to "/scenes": the same limit
        for route_method, pattern, limit in self.limits:
            if route_method == method and pattern.match(path):
                return limit
        return self.default

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, path = scope["method"], scope["path"]
        limit = self.limit_of(method, path)
        declared = _content_length(scope)
        if declared is not None and declared > limit.max_bytes:
            await _refuse(send, method, path, limit)
            return

        received = 0
        exceeded = False
        started = False

        async def limited_receive():
            nonlocal received, exceeded
            if exceeded:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit.max_bytes:
                    exceeded = True
                    raise BodyTooLarge(f"request body larger than {limit.max_bytes} bytes")
            return message

        async def guarded_send(message):
            nonlocal started
            if exceeded:
                return  # the app's answer to a cut-off body; the 413 below replaces it
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except Exception:
            if not exceeded:
                raise
        if exceeded and not started:
            await _refuse(send, method, path, limit)


def _content_length(scope) -> int | None:
    for name, value in scope.get("headers", ()):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None  # the server refuses a malformed one before we get here
    return None


async def _refuse(send, method: str, path: str, limit: Limit) -> None:
    env = f"RAYFARM_{limit.setting.upper()}"
    body = json.dumps({"detail": f"request body too large: {method} {path} accepts at most "
                                 f"{limit.max_bytes} bytes ({_round_size(limit.max_bytes)}{env})"}
                      ).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


def install_body_limits(app, settings: Settings) -> None:
    """Limit every route's body: POST /scenes (uploads) and POST /jobs (inline
    scene documents) to their own settings, the rest to `max_body_bytes`."""
    app.add_middleware(BodyLimit, default=Limit(settings.max_body_bytes, "max_body_bytes"),
                       limits={
                           ("POST", "/scenes"): Limit(settings.max_upload_bytes,
                                                      "max_upload_bytes"),
                           ("POST", "/jobs"): Limit(settings.max_job_bytes, "max_job_bytes"),
                       })
