"""The ledger's engine and sessions, built from settings (never at import).

    engine, sessions = open_ledger(settings)
    with sessions.begin() as session:
        session.add(job)
"""

from __future__ import annotations

from sqlalchemy import Engine, create_engine, event, inspect
from sqlalchemy.schema import CreateColumn
from sqlalchemy.orm import Session, sessionmaker

from .models import Base
from .settings import Settings

__all__ = ["open_ledger"]


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    # WAL lets the API read while the scheduler writes; busy_timeout makes a
    # writer wait for the lock instead of failing at once.
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    # In WAL mode NORMAL syncs at checkpoints, not at every commit: a power
    # cut may lose the last commits, never the ledger's consistency. What a
    # lost commit said (a unit done, its film already fsynced by the store) is
    # rendered again. FULL cost an fsync per landed unit on the scheduler's
    # thread: a progressive job's 200 units paid it 200 times.
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.close()


def open_ledger(settings: Settings) -> tuple[Engine, sessionmaker[Session]]:
    """Connect to the ledger (creating its tables) and return (engine, session factory)."""
    url = settings.sqlalchemy_url
    if url.startswith("sqlite"):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})
        event.listen(engine, "connect", _sqlite_pragmas)
    else:
        engine = create_engine(url, pool_pre_ping=True)
    Base.metadata.create_all(engine)
    _add_missing_columns(engine)
    return engine, sessionmaker(engine, expire_on_commit=False)


def _add_missing_columns(engine: Engine) -> None:
    """A ledger from an older version lacks the newer columns (all with server
    defaults, or nullable): add them. Nothing is ever dropped or changed."""
    inspector = inspect(engine)
    for table in Base.metadata.sorted_tables:
        present = {c["name"] for c in inspector.get_columns(table.name)}
        missing = [c for c in table.columns if c.name not in present]
        if not missing:
            continue
        with engine.begin() as conn:
            for column in missing:
                ddl = CreateColumn(column).compile(dialect=engine.dialect)
                conn.exec_driver_sql(f"ALTER TABLE {table.name} ADD COLUMN {ddl}")
