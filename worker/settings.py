"""The one settings class of rayfarm, shared by the service and the worker.

Read from the environment with the prefix ``RAYFARM_`` (``RAYFARM_BROKER_URL``,
``RAYFARM_DATA_DIR``, ...). Nothing builds it at import time: the CLI and the
tests construct it and hand it down::

    settings = Settings(data_dir="/tmp/farm", broker_url="redis://localhost:6379/0")
"""

from __future__ import annotations

import json
import os
import stat
from typing import Annotated, Literal
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from renderer import DEFAULT_MAX_WORK

__all__ = ["AdminLimits", "RoleLimits", "Settings"]


class RoleLimits(BaseModel):
    """What one role may ask of the farm (admission control); the defaults are an
    artist's. Set one field from the environment with a double underscore:
    ``RAYFARM_LIMITS_ARTIST__MAX_ACTIVE_JOBS=5``."""

    model_config = ConfigDict(extra="forbid")

    max_samples_per_job: int = Field(1 << 30, gt=0,
                                     description="width x height x spp of one job")
    max_units_per_job: int = Field(16384, gt=0,
                                   description="work units one job may be planned into")
    max_active_jobs: int = Field(50, ge=0,
                                 description="queued, running or paused jobs of one owner")
    submissions_per_minute: int = Field(60, ge=0, description="jobs submitted per token and "
                                                               "minute, an experiment's each "
                                                               "(429 with Retry-After above)")
    uploads_per_hour: int = Field(120, ge=0, description="POST /scenes per owner and hour")
    # Memory (renderer/memory.py says what a job holds). The defaults are
    # sized for a machine of 24 GB: an artist's job at most a quarter of it,
    # an admin's half (docs/hardening.md has the figures).
    max_pixels_per_job: int = Field(4096 * 4096, gt=0, description="width x height of one job")
    max_unit_bytes: int = Field(1 << 30, gt=0,
                                description="bytes a render process may hold for one work unit "
                                            "of a job: its film (whole-frame splats included), "
                                            "scratch and inputs")
    max_job_bytes: int = Field(6 << 30, gt=0,
                               description="bytes one job may hold at once: the service's "
                                           "share (running frames, landed films, the merge) "
                                           "plus a unit in each render process "
                                           "(local_workers)")
    # Disk: unit films stay in the store until their job is deleted.
    max_job_store_bytes: int = Field(16 << 30, gt=0,
                                     description="bytes one job's unit films may take in the "
                                                 "store (renderer/memory.py: BDPT stores the "
                                                 "frame's splats with every tile of every pass)")


class AdminLimits(RoleLimits):
    """An admin's limits: the farm's own caps."""

    max_samples_per_job: int = Field(DEFAULT_MAX_WORK, gt=0)
    max_units_per_job: int = Field(65536, gt=0)
    max_active_jobs: int = Field(1000, ge=0)
    submissions_per_minute: int = Field(600, ge=0)
    uploads_per_hour: int = Field(1000, ge=0)
    max_pixels_per_job: int = Field(8192 * 8192, gt=0)
    max_unit_bytes: int = Field(4 << 30, gt=0)
    max_job_bytes: int = Field(12 << 30, gt=0)
    max_job_store_bytes: int = Field(64 << 30, gt=0)


class Settings(BaseSettings):
    """Configuration of a rayfarm deployment (service and workers)."""

    model_config = SettingsConfigDict(env_prefix="RAYFARM_", extra="ignore",
                                      env_nested_delimiter="__")

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
        60.0, gt=0, description="a started unit whose heartbeat was not seen this long, or a "
                                "queued unit missing from an empty queue this long, is "
                                "enqueued again")
    max_attempts: int = Field(3, ge=1, description="attempts of a failing unit before its job fails")
    unit_budget_factor: float = Field(
        10.0, gt=0, description="a rendering unit is stopped (a failed attempt) once it has "
                                "run this many times as long as its samples take at the "
                                "measured rate (service/budget.py)")
    unit_budget_floor: float = Field(
        120.0, gt=0, description="seconds a unit may always render, whatever the measured "
                                 "rate says (short units are never stopped for time)")
    preemption: bool = Field(
        True, description="while an owner waits for a render process, stop (and later "
                          "render again) a unit of an owner holding more than its share "
                          "(service/fairshare.py)")
    preempt_after_seconds: float = Field(
        2.0, ge=0, description="a unit that has rendered less than this is never preempted "
                               "(short units free their process on their own)")
    worker_failures_per_job: int = Field(
        3, ge=0, description="failed units of one job on one worker before that worker is "
                             "blocklisted for the job (its units go to other workers; when "
                             "every live worker is blocklisted the job fails); 0 = never")
    local_workers: int = Field(default_factory=lambda: os.cpu_count() or 1, ge=1,
                               description="processes of the embedded pool")
    poll_interval: float = Field(0.2, gt=0, description="seconds between scheduler ticks")
    leader_lease_seconds: float = Field(
        5.0, gt=0, description="the scheduler lease of the service replicas on one ledger: "
                               "a standby takes over this long after the leader stopped "
                               "renewing it (on SQLite at once when the leader's process "
                               "died); the leader stops scheduling after half of it")
    worker_heartbeat_seconds: float = Field(
        2.0, gt=0, description="how often a Celery worker reports that it is alive; a "
                               "rendering unit's own heartbeat lives three times this long")
    worker_lost_seconds: float = Field(
        10.0, gt=0, description="a worker silent this long is lost: shown so, and the units it "
                                "was rendering are enqueued again at once")
    max_upload_bytes: int = Field(64 * 1024 * 1024, gt=0,
                                  description="largest request body of POST /scenes (413 above)")
    max_upload_files: int = Field(
        4096, ge=0, description="most files in one POST /scenes: the files sent beside the "
                                "scene file, or the members of an archive (folders included)")
    max_upload_unpacked_bytes: int = Field(
        1 << 30, gt=0, description="bytes an upload's files may hold once an archive is "
                                   "unpacked (counted while unpacking, 413 above)")
    max_upload_ratio: float = Field(
        200.0, gt=1, description="most an archive member (a compressed tar: the whole tar) may "
                                 "unpack to, in times its compressed size, past its first MiB "
                                 "(413 above: a decompression bomb)")
    max_upload_depth: int = Field(16, ge=1, description="most folders deep a path in an upload "
                                                        "may be")
    max_upload_path_bytes: int = Field(1024, ge=16, description="longest path in an upload, in "
                                                                "UTF-8 bytes")
    upload_check_seconds: float = Field(
        600.0, gt=0, description="longest an upload's check (unpacking, importing, storing) "
                                 "may take; its process is then stopped (413)")
    max_concurrent_uploads: int = Field(
        4, ge=1, description="POST /scenes received and checked at once by one service (each "
                             "checks its files in a child process); 429 with Retry-After above")
    max_job_bytes: int = Field(16 * 1024 * 1024, gt=0,
                               description="largest request body of POST /jobs (413 above)")
    max_body_bytes: int = Field(64 * 1024, gt=0,
                                description="largest request body of every other route: a "
                                            "login, a user, a token, a job's change, an "
                                            "experiment (413 above)")
    cache_dir: Path | None = Field(
        None, description="the renderer's on-disk caches (radiosity solutions, in "
                          "<cache_dir>/radiosity); empty = <data_dir>/cache")
    cache_max_bytes: int = Field(1 << 30, gt=0,
                                 description="size cap of each on-disk cache; the least "
                                             "recently used entries are evicted above it")
    log_format: Literal["text", "json"] = Field(
        "text", description="json: `rayfarm serve` and workers log one JSON object per line "
                            "(time, level, logger, message, job_id and unit when known)")
    min_free_bytes: int = Field(256 * 1024 * 1024, ge=0,
                                description="below this much free space on the data dir's "
                                            "file system, /healthz reports degraded and new "
                                            "jobs, scenes and experiments are refused (507)")
    umask: str = Field("077", pattern=r"^0?[0-7]{3}$",
                       description="permission bits (octal) withheld from every file and "
                                   "directory that `rayfarm serve`, `rayfarm worker` and the "
                                   "admin commands create: 077 = their user's alone (files "
                                   "0600, directories 0700, the SQLite ledger's -wal and "
                                   "-shm too); 027 lets the group read")

    # -- accounts and admission (service only) ------------------------------------
    admin_token: str = Field(
        "", description="the first admin's token, when the ledger has no admin yet; empty = "
                        "a random one, printed in the login URL and kept in "
                        "<data_dir>/admin.token (mode 0600)")
    session_hours: float = Field(168.0, gt=0, description="lifetime of a dashboard login")
    cors_origins: list[str] = Field(
        default_factory=list, description="origins allowed to call the API from a browser "
                                          "(CORS); empty = none, same origin only")
    allowed_hosts: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="the names the service answers to (the Host header; "
                                          "comma-separated, '*.example.com' for a domain's, "
                                          "'*' for any); localhost, 127.0.0.1 and ::1 always; "
                                          "empty = the address `rayfarm serve --host` listens "
                                          "on (every name of this machine for 0.0.0.0)")
    limits_admin: AdminLimits = Field(default_factory=AdminLimits)
    limits_artist: RoleLimits = Field(default_factory=RoleLimits)

    @field_validator("cache_dir", mode="before")
    @classmethod
    def _empty_cache_dir(cls, value):
        return None if isinstance(value, str) and not value.strip() else value

    @model_validator(mode="after")
    def _default_cache_dir(self) -> "Settings":
        if self.cache_dir is None:
            self.cache_dir = self.data_dir / "cache"
        return self

    def keep_files_private(self) -> None:
        """Make `umask` this process's, and take its bits off the data directory
        if it exists (made by an older version, or before the setting changed):
        what it holds is then out of others' reach too. Called at the start of
        the commands that write there; a program that embeds the service
        (`create_app`) keeps its own umask."""
        mask = int(self.umask, 8)
        os.umask(mask)
        try:
            mode = stat.S_IMODE(self.data_dir.stat().st_mode)
            if mode & mask:
                self.data_dir.chmod(mode & ~mask)
        except OSError:  # not there yet (made under the umask), or not ours
            pass

    def configure_renderer(self) -> None:
        """Point the renderer's on-disk caches at `cache_dir` with `cache_max_bytes`
        (the service and the Celery worker call this at start)."""
        from renderer import cache

        cache.configure(self.cache_dir, self.cache_max_bytes)

    @field_validator("allowed_hosts", mode="before")
    @classmethod
    def _split_hosts(cls, value):
        # From the environment: "farm.example.com,10.0.0.5" (or a JSON list, as other lists)
        if isinstance(value, str):
            text = value.strip()
            return json.loads(text) if text.startswith("[") else [
                name.strip() for name in text.split(",") if name.strip()]
        return value

    @field_validator("log_format", mode="before")
    @classmethod
    def _lower_log_format(cls, value):
        return value.strip().lower() if isinstance(value, str) else value

    @field_validator("broker_url", "database_url", "admin_token")
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
