"""Dependencies as `Annotated` aliases, overridable with `app.dependency_overrides`;
and `unicode_body`, which every route has (service.main)."""

from __future__ import annotations

from typing import Annotated, Iterator

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from ..errors import InvalidRequest
from ..farm import Farm
from ..settings import Settings
from ..store import Store
from ..text import lone_surrogate

__all__ = ["FarmDep", "SessionDep", "SettingsDep", "StoreDep", "unicode_body"]


def get_farm(request: Request) -> Farm:
    return request.app.state.farm


FarmDep = Annotated[Farm, Depends(get_farm)]


def get_session(farm: FarmDep) -> Iterator[Session]:
    with farm.sessions() as session:
        yield session


def get_settings(farm: FarmDep) -> Settings:
    return farm.settings


def get_store(farm: FarmDep) -> Store:
    return farm.store


SessionDep = Annotated[Session, Depends(get_session)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[Store, Depends(get_store)]


# -- text that is not text ---------------------------------------------------------------

async def unicode_body(request: Request) -> None:
    """422 naming the field for a JSON body with a lone surrogate in a string
    (service.text): every route has this dependency (service.main)."""
    route = request.scope.get("route")
    if getattr(route, "body_field", None) is None or request.method in ("GET", "HEAD"):
        return
    try:
        document = await request.json()  # parsed already by FastAPI: its cached result
    except Exception:  # not JSON: FastAPI has answered or will answer for it
        return
    found = lone_surrogate(document)
    if found is not None:
        field, text = found
        raise InvalidRequest(field or "body", f'not valid Unicode text: "{text[:60]}" holds a '
                                              "lone surrogate (half of a UTF-16 pair, or its "
                                              "UTF-8 bytes ED A0..BF)")
