"""Dependencies as `Annotated` aliases, overridable with `app.dependency_overrides`."""

from __future__ import annotations

from typing import Annotated, Iterator

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from ..farm import Farm
from ..settings import Settings
from ..store import Store

__all__ = ["FarmDep", "SessionDep", "SettingsDep", "StoreDep"]


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
