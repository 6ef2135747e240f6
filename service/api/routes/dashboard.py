"""The web dashboard at `/` (a static single-page app in service/static) and the
API docs at `/docs` and `/redoc`, every asset served by rayfarm itself, so
both work on a machine without internet access.

`/?token=<token>` is the login URL the service prints when it starts (as
Jupyter does): the token is traded for the dashboard's session cookie and the
browser is sent on to `/`, so the token leaves the address bar and history.
The pages and assets are public; every piece of data they show comes from
the API, which needs a login. The OpenAPI schema needs one too.

The link is traded at once only for a navigation the user made: typed,
pasted, a bookmark, or clicked in a terminal or mail program (the browser's
`Sec-Fetch-Site: none`), or from this dashboard itself (`same-origin`).
From anywhere else (another site, even another port of this host, or a
browser that does not say) a link could be someone else's token, logging
this browser into their account: what the victim uploads next would be
theirs (login CSRF). Then the dashboard is served as it is, and its login
page takes the token out of the address bar and asks first, naming the user
the link would log in as; the login is its POST /auth/login, which refuses
another origin.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse
from starlette.concurrency import run_in_threadpool
from starlette.staticfiles import StaticFiles

from ... import auth
from ...errors import Unauthorized
from ...models import utcnow
from ..auth import PROTECTED, set_login_cookies
from ..deps import FarmDep

__all__ = ["router", "mount_assets", "STATIC_DIR"]

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
DOCS_ASSETS = "/docs-assets"  # Swagger UI and ReDoc bundles, from the fastapi-offline package
OPENAPI_URL = "/openapi.json"

router = APIRouter(include_in_schema=False)
# Sec-Fetch-Site of a navigation the user made (module doc)
USER_NAVIGATION = ("none", "same-origin")


class _RevalidatedFiles(StaticFiles):
    """Static files that browsers revalidate (ETag) on every use, so a new
    version of the dashboard is picked up without a hard reload."""

    def file_response(self, *args, **kwargs):
        response = super().file_response(*args, **kwargs)
        response.headers["Cache-Control"] = "no-cache"
        return response


def mount_assets(app: FastAPI) -> None:
    app.mount("/static", _RevalidatedFiles(directory=STATIC_DIR), name="static")
    docs = resources.files("fastapi_offline") / "static"
    app.mount(DOCS_ASSETS, StaticFiles(directory=str(docs)), name="docs-assets")


@router.get("/", response_model=None)
async def index(request: Request, farm: FarmDep,
                token: str | None = None) -> FileResponse | RedirectResponse:
    if token is None or request.headers.get("sec-fetch-site") not in USER_NAVIGATION:
        # the dashboard's login page asks before it uses a link's token
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html",
                            headers={"Cache-Control": "no-cache"})

    def trade():
        with farm.sessions.begin() as session:
            return auth.create_session(session, token, utcnow(), farm.settings.session_hours)

    try:
        _, session_secret = await run_in_threadpool(trade)
    except Unauthorized:  # the dashboard's login page says so
        return RedirectResponse("/#/login?failed=1", status_code=303)
    response = RedirectResponse("/", status_code=303)
    set_login_cookies(response, request, session_secret, int(farm.settings.session_hours * 3600))
    return response


@router.get(OPENAPI_URL, dependencies=PROTECTED)
def openapi(request: Request) -> JSONResponse:
    return JSONResponse(request.app.openapi())


@router.get("/docs")
def swagger_ui(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(openapi_url=OPENAPI_URL, title="rayfarm API",
                               swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
                               swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
                               swagger_favicon_url="/static/favicon.svg",
                               # no badge from the online validator: nothing leaves this host
                               swagger_ui_parameters={"validatorUrl": None})


@router.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    return get_redoc_html(openapi_url=OPENAPI_URL, title="rayfarm API",
                          redoc_js_url=f"{DOCS_ASSETS}/redoc.standalone.js",
                          redoc_favicon_url="/static/favicon.svg", with_google_fonts=False)
