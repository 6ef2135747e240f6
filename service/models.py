"""The job ledger's tables: `jobs` and their work `units` (SQLAlchemy 2), the
uploaded `scenes` and who claims them, the farm's `users` and their `tokens`,
the `scheduler_lease` that says which service replica schedules, and the
`service_replicas` that serve on the ledger (and the data dir each uses).

Both carry a version counter (optimistic locking): the API (cancel) and the
scheduler (progress) change the same rows from different threads or
processes, and a write based on a stale read fails instead of overwriting.
Status values and their changes belong to `service.states`.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone

from sqlalchemy import (JSON, BigInteger, Boolean, DateTime, Float, ForeignKey, Integer, String,
                        Text, text)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

__all__ = ["ApiToken", "Base", "Experiment", "Job", "SceneClaim", "SceneRecord", "SchedulerLease",
           "ServiceReplica", "User",
           "WorkUnit", "WorkerBlock", "utcnow"]


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every database (SQLite forgets the zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is not None and value.tzinfo is None:
            raise ValueError("naive datetime; use service.models.utcnow()")
        return value.astimezone(timezone.utc) if value is not None else None

    def process_result_value(self, value, dialect):
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value


class Base(DeclarativeBase):
    pass


class Job(Base):
    """A render job: what to render, its status and its progress."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    version: Mapped[int] = mapped_column(Integer, nullable=False)
    created: Mapped[datetime] = mapped_column(UTCDateTime, index=True)
    started: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished: Mapped[datetime | None] = mapped_column(UTCDateTime)
    status: Mapped[str] = mapped_column(String(16), index=True)
    # The user who submitted it (`users.name`): who may see and change it, and
    # whose fair share its units count against. Jobs from before accounts: "admin".
    owner: Mapped[str] = mapped_column(String(64), index=True, default="admin",
                                       server_default=text("'admin'"))
    scene: Mapped[str] = mapped_column(String(200))
    scene_hash: Mapped[str] = mapped_column(String(64))
    spec: Mapped[dict] = mapped_column(JSON)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    units_total: Mapped[int] = mapped_column(Integer, default=0)
    units_done: Mapped[int] = mapped_column(Integer, default=0)
    error: Mapped[str | None] = mapped_column(Text)
    samples: Mapped[int] = mapped_column(BigInteger, default=0)
    rays: Mapped[int] = mapped_column(BigInteger, default=0)
    # Higher first; changeable while the job waits or runs (PATCH /jobs/{id}).
    priority: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    # Planned as tiles x sample passes (1, 1, 2, 4, ... spp), so the preview improves.
    progressive: Mapped[bool] = mapped_column(Boolean, default=False,
                                              server_default=text("false"))
    # Denoise the merged frame once it is done (renderer.denoise): denoised.R/G/B
    # in the EXR beside the raw beauty, and denoised.png.
    denoise: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))
    # Rendered to a noise target (renderer.target; service.targets): the target
    # as JSON {rel_error, max_spp, max_seconds} (spec["spp"] is max_spp), else None.
    target: Mapped[dict | None] = mapped_column(JSON)
    # A target job's units that may run: a prefix of its plan, the passes
    # decided so far (None: every unit, as for any other job).
    units_open: Mapped[int | None] = mapped_column(Integer)
    # Units a target job skipped: their region met the target before their pass
    # (counted in units_done too: finished without a film).
    units_skipped: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    # The image's error statistic (renderer.film.image_error) after the last
    # complete pass of a target job, and of the result once done; None before.
    rel_error: Mapped[float | None] = mapped_column(Float)
    # Why a target job stopped: "target", "max_spp" or "max_seconds" (None before).
    target_stop: Mapped[str | None] = mapped_column(String(16))
    # A target job's complete passes: [{pass, spp, samples, seconds, rel_error,
    # active}] (service.targets), the convergence it made and what its ETA reads.
    pass_log: Mapped[list | None] = mapped_column(JSON)
    # Time after its start the job could not run (finished pauses; failed until
    # retried) and the start of the current pause, so elapsed time, throughput
    # and ETA count only the time it could run.
    paused_seconds: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    paused_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # Sum of the done units' render seconds (as their workers measured) and the
    # number of done units that needed more than one task (lost or failed before).
    unit_seconds: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    units_retried: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    # Samples/s over roughly the last RATE_SECONDS (an exponential moving average
    # updated as units land) and when it was last updated: drives the ETA, which
    # the whole-job average would overestimate while early, overhead-bound
    # passes of a progressive job still weigh in.
    recent_rate: Mapped[float | None] = mapped_column(Float)
    recent_weight: Mapped[float | None] = mapped_column(Float)  # of the average's bias correction
    recent_rate_at: Mapped[datetime | None] = mapped_column(UTCDateTime)

    __mapper_args__ = {"version_id_col": version}

    @property
    def samples_total(self) -> int:
        """Camera samples the finished job will have taken: width x height x spp."""
        return self.width * self.height * int(self.spec["spp"])

    def note_samples(self, samples: int, now: datetime, window: float = 10.0) -> None:
        """Fold `samples` that landed at `now` into `recent_rate`: an exponential
        moving average of samples/s with time constant `window` seconds, bias
        corrected (divided by its total weight, as Adam does) so that its first
        values are plain averages, not pulled towards zero.

        The first landing since the job (re)started only starts the
        measurement: its wait held the queue, and for the first job after a
        start the render processes loading their kernels, so counting it made
        a 50-s job's first ETA 45 minutes. `recent_rate` stays None (and the
        job shows no ETA) until a second landing measures a real rate."""
        if self.recent_weight is None:
            self.recent_weight, self.recent_rate, self.recent_rate_at = 0.0, None, now
            return
        since = self.recent_rate_at or self.started or now
        dt = max((now - since).total_seconds(), 1e-3)
        alpha = 1.0 - math.exp(-dt / window)
        weight = self.recent_weight or 0.0
        raw = (self.recent_rate or 0.0) * weight * (1.0 - alpha) + alpha * samples / dt
        self.recent_weight = weight * (1.0 - alpha) + alpha
        self.recent_rate = raw / self.recent_weight
        self.recent_rate_at = now

    def active_seconds(self, now: datetime) -> float | None:
        """Seconds since the start (until the finish) that the job could run:
        pauses, and time spent failed before a retry, excluded. None before the start."""
        if self.started is None:
            return None
        end = self.finished or (self.paused_at if self.status == "paused" else None) or now
        return max((end - self.started).total_seconds() - (self.paused_seconds or 0.0), 0.0)


class WorkUnit(Base):
    """One work unit of a job, as planned (`unit`: the renderer's Unit dict)."""

    __tablename__ = "units"

    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"),
                                        primary_key=True)
    index: Mapped[int] = mapped_column(Integer, primary_key=True)
    version: Mapped[int] = mapped_column(Integer, nullable=False)
    state: Mapped[str] = mapped_column(String(16), index=True)
    unit: Mapped[dict] = mapped_column(JSON)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    task_ids: Mapped[list] = mapped_column(JSON, default=list)
    worker: Mapped[str | None] = mapped_column(String(200))
    enqueued_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    seconds: Mapped[float | None] = mapped_column(Float)
    error: Mapped[str | None] = mapped_column(Text)
    # Why it was last enqueued again without spending an attempt (its worker
    # lost, its lease lapsed, its message lost, declined by a worker); None if never.
    requeue_reason: Mapped[str | None] = mapped_column(Text)
    # SHA-256 of the stored film (set when the unit is done): later units of a
    # DAG job receive their inputs by it (service.artefacts).
    film_digest: Mapped[str | None] = mapped_column(String(64))

    __mapper_args__ = {"version_id_col": version}


class Experiment(Base):
    """An estimator-lab experiment (service.experiments): configurations x spp
    levels x repeats rendered as ordinary jobs (`runs`: one entry per job,
    {"config", "spp", "repeat", "job"}), a reference job, and once every job
    is done the measured report (renderer.lab)."""

    __tablename__ = "experiments"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    version: Mapped[int] = mapped_column(Integer, nullable=False)
    owner: Mapped[str] = mapped_column(String(64), index=True)
    created: Mapped[datetime] = mapped_column(UTCDateTime)
    finished: Mapped[datetime | None] = mapped_column(UTCDateTime)
    status: Mapped[str] = mapped_column(String(16), index=True)  # running, done, failed, canceled
    request: Mapped[dict] = mapped_column(JSON)
    runs: Mapped[list] = mapped_column(JSON)
    reference_job: Mapped[str] = mapped_column(String(32))
    report: Mapped[dict | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)

    __mapper_args__ = {"version_id_col": version}


class WorkerBlock(Base):
    """The failed units of one job on one worker (Deadline's and Flamenco's
    habit): at `settings.worker_failures_per_job` the worker is blocklisted for
    the job (`blocked`), its units go to other workers. The job's owner or an
    admin clears it (the row goes). Rows go with their job."""

    __tablename__ = "worker_blocks"

    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"),
                                        primary_key=True)
    worker: Mapped[str] = mapped_column(String(200), primary_key=True)
    failures: Mapped[int] = mapped_column(Integer, default=0)
    last_error: Mapped[str | None] = mapped_column(Text)
    blocked: Mapped[datetime | None] = mapped_column(UTCDateTime)


class SceneRecord(Base):
    """An uploaded scene. Its resolved text lives in the store under `id` (its
    content hash) and stays there when the record is deleted: jobs carry it."""

    __tablename__ = "scenes"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    created: Mapped[datetime] = mapped_column(UTCDateTime, index=True)
    triangles: Mapped[int] = mapped_column(BigInteger)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    bytes: Mapped[int] = mapped_column(BigInteger, doc="length of the resolved canonical text")
    # The upload's main file (its path in the upload's folder) and its import
    # report: a JSON list of {element, file, line, action}, what the importer
    # did not take as written. Records from before importers: "" and "[]".
    source: Mapped[str] = mapped_column(String(1024), default="", server_default=text("''"))
    report: Mapped[str] = mapped_column(Text, default="[]", server_default=text("'[]'"))
    # A job's depth when it gives none (renderer.spec.default_depth of the
    # document: an imported file's max_depth), kept so that a job need not
    # parse the stored text. NULL in records from before it: read the text.
    default_depth: Mapped[int | None] = mapped_column(Integer, nullable=True)


class SceneClaim(Base):
    """An owner's claim on an uploaded scene. The scene (its text, its record)
    is shared by content hash; each owner who uploaded it sees it, and deleting
    it removes only that owner's claim (the record goes with the last one)."""

    __tablename__ = "scene_claims"

    scene_id: Mapped[str] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"),
                                          primary_key=True)
    owner: Mapped[str] = mapped_column(String(64), primary_key=True)
    created: Mapped[datetime] = mapped_column(UTCDateTime)


class User(Base):
    """A person (or a pipeline) using the farm, with a role (`service.access`)."""

    __tablename__ = "users"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    role: Mapped[str] = mapped_column(String(16))
    # Weight of the user's jobs in the fair share between owners (OpenCue's
    # "shares", Deadline's weights): units in flight are split in proportion.
    share: Mapped[float] = mapped_column(Float, default=1.0, server_default=text("1"))
    created: Mapped[datetime] = mapped_column(UTCDateTime)
    disabled: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))


class ApiToken(Base):
    """A bearer token, stored only as the SHA-256 of its secret (the secret is
    shown once, at creation). `kind` "api" is a token a person or a script
    holds; "session" is a dashboard login made from one (`parent`), which dies
    with it."""

    __tablename__ = "tokens"

    id: Mapped[str] = mapped_column(String(16), primary_key=True)
    user: Mapped[str] = mapped_column(ForeignKey("users.name", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16), default="api")
    parent: Mapped[str | None] = mapped_column(String(16))
    secret_hash: Mapped[str] = mapped_column(String(64), unique=True)
    label: Mapped[str] = mapped_column(String(200), default="")
    created: Mapped[datetime] = mapped_column(UTCDateTime)
    expires: Mapped[datetime | None] = mapped_column(UTCDateTime)
    revoked: Mapped[datetime | None] = mapped_column(UTCDateTime)
    last_used: Mapped[datetime | None] = mapped_column(UTCDateTime)


class SchedulerLease(Base):
    """Which service replica runs the scheduler (`service.leader`). Its times
    are the ledger's clock; `epoch` grows with every new holder."""

    __tablename__ = "scheduler_lease"

    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    holder: Mapped[str] = mapped_column(String(200))
    epoch: Mapped[int] = mapped_column(BigInteger)
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime)
    acquired_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    renewed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class ServiceReplica(Base):
    """A `rayfarm serve` on this ledger and the data dir it uses (`service.leader`):
    it beats `seen_at` (the ledger's clock) while it lives and goes when it stops.
    `data_dir_id` is the data dir's own id (`service.store.data_dir_identity`),
    the same under any path or host that mounts it."""

    __tablename__ = "service_replicas"

    identity: Mapped[str] = mapped_column(String(200), primary_key=True)
    data_dir: Mapped[str] = mapped_column(Text)  # as this replica names it, for messages
    data_dir_id: Mapped[str] = mapped_column(String(64))
    started: Mapped[datetime] = mapped_column(UTCDateTime)
    seen_at: Mapped[datetime] = mapped_column(UTCDateTime, index=True)
