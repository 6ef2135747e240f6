"""The one settings class (RAYFARM_* environment), shared by service and worker."""

from __future__ import annotations

import os


def test01_defaults_and_urls(tmp_path, monkeypatch):
    from renderer import DEFAULT_MAX_WORK
    from service.settings import Settings

    for key in [k for k in os.environ if k.startswith("RAYFARM_")]:
        monkeypatch.delenv(key)
    settings = Settings()
    assert settings.broker_url == "" and settings.max_work == DEFAULT_MAX_WORK
    assert settings.unit_lease_seconds == 60 and settings.poll_interval == 0.2
    assert settings.sqlalchemy_url.startswith("sqlite:///") and settings.sqlalchemy_url.endswith(
        "rayfarm-data/rayfarm.sqlite3")
    monkeypatch.setenv("RAYFARM_DATABASE_URL", "postgresql://db:5432/farm")
    monkeypatch.setenv("RAYFARM_LOCAL_WORKERS", "3")
    settings = Settings()
    assert settings.sqlalchemy_url == "postgresql+psycopg://db:5432/farm"
    assert settings.local_workers == 3
