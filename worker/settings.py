"""The one settings class of rayfarm, shared by the service and the worker.

Read from the environment with the prefix ``RAYFARM_`` (``RAYFARM_BROKER_URL``,
``RAYFARM_DATA_DIR``, ...). Nothing builds it at import time: the CLI and the
tests construct it and hand it down::

    settings = Settings(data_dir="/tmp/farm", broker_url="redis://localhost:6379/0")
"""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from renderer import DEFAULT_MAX_WORK

__all__ = ["Settings"]


class Settings(BaseSettings):
    """Configuration of a rayfarm deployment (service and workers)."""

    model_config = SettingsConfigDict(env_prefix="RAYFARM_", extra="ignore")

    broker_url: str = Field(
        "", description="Redis URL of the Celery broker and result backend; "
                        "empty = run units on the service's embedded process pool")
    database_url: str = Field(
        "", description="SQLAlchemy URL of the job ledger; empty = SQLite file in data_dir")
    data_dir: Path = Field(Path("./rayfarm-data"),
                           description="where scenes, unit films and results are stored")
    max_work: int = Field(DEFAULT_MAX_WORK, gt=0,
                          description="largest accepted job: width x height x spp")
    max_units: int = Field(65536, gt=0, description="largest accepted number of work units")
    unit_lease_seconds: float = Field(
        60.0, gt=0, description="a started unit whose heartbeat is absent this long, or a "
                                "queued unit missing from an empty queue this long, is "
                                "enqueued again")
    max_attempts: int = Field(3, ge=1, description="attempts of a failing unit before its job fails")
    local_workers: int = Field(default_factory=lambda: os.cpu_count() or 1, ge=1,
                               description="processes of the embedded pool")
    poll_interval: float = Field(0.2, gt=0, description="seconds between scheduler ticks")
    worker_heartbeat_seconds: float = Field(
        2.0, gt=0, description="how often a Celery worker reports that it is alive")
    worker_lost_seconds: float = Field(
        10.0, gt=0, description="a worker silent this long is shown as lost")
    max_upload_bytes: int = Field(64 * 1024 * 1024, gt=0,
                                  description="largest request body of POST /scenes (413 above)")
    max_upload_files: int = Field(64, ge=0, description="most mesh files in one POST /scenes")
    max_job_bytes: int = Field(16 * 1024 * 1024, gt=0,
                               description="largest request body of POST /jobs (413 above)")

    @field_validator("broker_url", "database_url")
    @classmethod
    def _strip(cls, value: str) -> str:
        return value.strip()

    @property
    def sqlalchemy_url(self) -> str:
        """The ledger's URL: `database_url`, or SQLite at ``<data_dir>/rayfarm.sqlite3``.
        A plain ``postgresql://`` URL gets the installed psycopg (3) driver."""
        url = self.database_url
        for plain in ("postgresql://", "postgres://"):
            if url.startswith(plain):
                return "postgresql+psycopg://" + url[len(plain):]
        if url:
            return url
        return f"sqlite:///{(self.data_dir / 'rayfarm.sqlite3').resolve()}"
