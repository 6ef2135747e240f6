"""Security headers on every answer, as a pure ASGI middleware (it never
buffers a body, so event streams stay streams).

The dashboard is plain ES modules and one stylesheet served from here, with no
inline script or style, so its policy allows only 'self'. Swagger UI and
ReDoc (/docs, /redoc) start from an inline script and ReDoc styles inline,
so those two pages get a policy that allows inline code but still loads
nothing from another host.
"""

from __future__ import annotations

__all__ = ["SecurityHeaders", "CSP", "DOCS_CSP"]

CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
       "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; "
       "form-action 'self'; frame-ancestors 'none'")
DOCS_CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline'; "
            "style-src 'self' 'unsafe-inline'; img-src 'self' data:; worker-src 'self' blob:; "
            "connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'")
_COMMON = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    # The login URL carries a token: never send the address on to anyone.
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
    (b"cross-origin-resource-policy", b"same-origin"),
]
_DOCS_PATHS = ("/docs", "/redoc")


class SecurityHeaders:
    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        policy = (DOCS_CSP if scope["path"].rstrip("/") in _DOCS_PATHS else CSP).encode()

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", [])
                           if k.lower() not in _NAMES]
                headers += _COMMON + [(b"content-security-policy", policy)]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


_NAMES = {name for name, _ in _COMMON} | {b"content-security-policy"}
