"""Security headers on every answer, the names the service answers to, and
redirects that never repeat the request's Host: pure ASGI middleware (they
never buffer a body, so event streams stay streams).

    app.add_middleware(AllowedHosts, hosts=allowed_hosts(settings))   # 400 for another Host
    app.add_middleware(SecurityHeaders)
    relative_slash_redirects(app.router)     # /jobs/ -> 307 Location: /jobs

A page of another site can make the browser send any Host it likes by
pointing its own name at this machine (DNS rebinding): the service answers
only to the names it is configured with (`RAYFARM_ALLOWED_HOSTS`; by
default the address `rayfarm serve` listens on and, always, localhost,
127.0.0.1 and ::1). And since a Host is the caller's word, no answer builds a
URL from it: Starlette's trailing-slash redirect did (`Location:
http://<Host>/jobs`); here it is relative, and the login redirects are too.

The dashboard is plain ES modules and one stylesheet served from here, with no
inline script or style, so its policy allows only 'self'. Swagger UI and
ReDoc (/docs, /redoc) start from an inline script and ReDoc styles inline,
so those two pages get a policy that allows inline code but still loads
nothing from another host.
"""

from __future__ import annotations

import json
import socket

from starlette.responses import RedirectResponse
from starlette.routing import Match

__all__ = ["SecurityHeaders", "CSP", "DOCS_CSP", "AllowedHosts", "allowed_hosts",
           "relative_slash_redirects", "LOOPBACK"]

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


# -- the names the service answers to -------------------------------------------------------

LOOPBACK = ("localhost", "127.0.0.1", "::1")  # this machine's own: always allowed
_WILDCARD_BINDS = ("", "0.0.0.0", "::")


def _machine_names() -> set[str]:
    """This machine's host name, its FQDN and the addresses they resolve to."""
    names: set[str] = set()
    try:
        for name in {socket.gethostname(), socket.getfqdn()}:
            names.add(name)
            for *_, address in socket.getaddrinfo(name, None):
                names.add(str(address[0]).split("%")[0])
    except OSError:
        pass
    return names


def allowed_hosts(configured: list[str], bind: str | None = None) -> list[str]:
    """The Host names to answer: the configured ones, else the address the
    service listens on (`bind`; every name of this machine for a wildcard);
    the loopback names always."""
    names = set(configured)
    if not names and bind is not None:
        names = _machine_names() if bind in _WILDCARD_BINDS else {bind}
    return sorted({_normalized(n) for n in names | set(LOOPBACK) if n.strip()})


def _normalized(name: str) -> str:
    return name.strip().lower().rstrip(".").removeprefix("[").removesuffix("]")


def host_name(header: str) -> str:
    """The name in a Host header, without its port or an IPv6 literal's brackets."""
    header = header.strip()
    if header.startswith("["):
        return _normalized(header.partition("]")[0])
    name, _, port = header.rpartition(":")
    if not name or ":" in name or not port.isdigit():  # no port (or a bare IPv6 literal)
        name = header
    return _normalized(name)


class AllowedHosts:
    """400 for a request whose Host is none of `hosts` ("*.example.com"
    matches a domain's names, "*" any)."""

    def __init__(self, app, hosts: list[str]):
        self.app = app
        self.any = "*" in hosts
        self.exact = {h for h in hosts if not h.startswith("*")}
        self.suffixes = tuple(h[1:] for h in hosts if h.startswith("*."))

    def allows(self, header: str) -> bool:
        name = host_name(header)
        return self.any or name in self.exact or (bool(name) and name.endswith(self.suffixes))

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        header = next((v.decode("latin-1") for k, v in scope.get("headers", ())
                       if k == b"host"), "")
        if self.allows(header):
            await self.app(scope, receive, send)
            return
        body = json.dumps({"detail": f"unknown host {header[:100]!r}: this service answers to "
                                     "the names in RAYFARM_ALLOWED_HOSTS"}).encode()
        await send({"type": "http.response.start", "status": 400,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})


# -- redirects ------------------------------------------------------------------------------

def relative_slash_redirects(router) -> None:
    """Starlette's redirect of `/jobs/` to `/jobs` (and back), with a relative
    Location: Starlette builds an absolute one from the request's Host."""
    not_found = router.default
    router.redirect_slashes = False

    async def default(scope, receive, send) -> None:
        path = scope.get("path", "")
        if scope["type"] == "http" and path != "/":
            other = path.rstrip("/") if path.endswith("/") else path + "/"
            # "//host" would be a URL of another host (scheme-relative): never redirect there
            if other.startswith("/") and not other.startswith("//"):
                moved = {**scope, "path": other}
                if any(route.matches(moved)[0] is not Match.NONE for route in router.routes):
                    query = scope.get("query_string", b"").decode("latin-1")
                    location = other + (f"?{query}" if query else "")
                    await RedirectResponse(location, status_code=307)(scope, receive, send)
                    return
        await not_found(scope, receive, send)

    router.default = default
