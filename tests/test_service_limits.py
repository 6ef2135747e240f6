"""Admission through the API: the role's limits refuse a job too big (samples,
units: 422 naming the field and the setting), an owner with too many active
jobs (429), a token submitting too fast and an owner uploading too often (429
with Retry-After). Its own small farm with low artist limits."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from conftest import ADMIN_HEADERS, TINY
from worker.settings import RoleLimits

LIMITS = RoleLimits(max_samples_per_job=1 << 24, max_units_per_job=20, max_active_jobs=2,
                    submissions_per_minute=6, uploads_per_hour=1)
LONG = dict(TINY, spp=4096, width=64, height=64, tile_size=32, progressive=False)  # 4 units


@pytest.fixture(scope="module")
def farm(tmp_path_factory):
    from service import auth
    from service.main import create_app
    from service.models import utcnow
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("limits"), broker_url="",
                        database_url="", local_workers=1, poll_interval=0.05,
                        limits_artist=LIMITS)
    app = create_app(settings)
    with TestClient(app, headers=ADMIN_HEADERS) as admin:
        def artist(name: str) -> TestClient:
            with app.state.farm.sessions.begin() as session:
                auth.add_user(session, name, "artist", utcnow())
                secret = auth.create_token(session, name, utcnow())[1]
            return TestClient(app, headers={"Authorization": f"Bearer {secret}"})
        admin.artist = artist
        yield admin


def test01_samples_and_units_per_job_are_limited_by_role(farm):
    ana = farm.artist("ana")
    big = ana.post("/jobs", json=dict(TINY, spp=8192, width=64, height=64))
    assert big.status_code == 422
    assert big.json()["detail"][0]["loc"] == ["body", "spp"]
    assert "RAYFARM_LIMITS_ARTIST__MAX_SAMPLES_PER_JOB" in big.text
    many = ana.post("/jobs", json=dict(TINY, tile_size=4, progressive=False))  # 64 tiles
    assert many.status_code == 422 and many.json()["detail"][0]["loc"] == ["body", "tile_size"]
    assert "RAYFARM_LIMITS_ARTIST__MAX_UNITS_PER_JOB" in many.text
    # An SPPM job is refused on its unit floor (an iteration's photons), before it is planned.
    sppm = ana.post("/jobs", json=dict(TINY, method="photon", spp=1000, width=8, height=8))
    assert sppm.status_code == 422 and "MAX_UNITS_PER_JOB" in sppm.text
    # The admin's limits are the farm's own.
    assert farm.post("/jobs", json=dict(TINY, tile_size=4)).status_code == 201


def test02_active_jobs_per_owner_then_submissions_per_token(farm):
    bob = farm.artist("bob")
    first, second = (bob.post("/jobs", json=LONG) for _ in range(2))
    assert first.status_code == second.status_code == 201
    third = bob.post("/jobs", json=LONG)
    assert third.status_code == 429 and third.headers["retry-after"] == "30"
    assert "RAYFARM_LIMITS_ARTIST__MAX_ACTIVE_JOBS" in third.text
    assert farm.artist("cat").post("/jobs", json=LONG).status_code == 201  # another owner
    for job in (first, second):
        assert bob.post(f"/jobs/{job.json()['id']}/cancel").status_code == 200
    # 3 submissions so far this minute; 3 more (refused or not, they count), then 429.
    for _ in range(3):
        assert bob.post("/jobs", json=dict(TINY, spp=0)).status_code == 422
    refused = bob.post("/jobs", json=TINY)
    assert refused.status_code == 429
    assert 1 <= int(refused.headers["retry-after"]) <= 60


def test03_uploads_per_owner_and_hour(farm):
    from test_service_scenes import room, scene_bytes, upload

    dan = farm.artist("dan")
    assert upload(dan, scene_bytes(room("limits-1"))).status_code == 201
    again = upload(dan, scene_bytes(room("limits-2")))
    assert again.status_code == 429 and int(again.headers["retry-after"]) > 3000


def test04_a_frame_too_big_to_hold_is_422_naming_the_field_and_the_setting(farm):
    """The artist's memory limits are the defaults: 4096^2 pixels a job, 1 GiB
    a unit's render process (renderer/memory.py)."""
    dora = farm.artist("dora")
    wide = dora.post("/jobs", json=dict(TINY, width=4097, height=4096, tile_size=64))
    assert wide.status_code == 422, wide.text
    assert wide.json()["detail"][0]["loc"] == ["body", "width"]
    assert "RAYFARM_LIMITS_ARTIST__MAX_PIXELS_PER_JOB" in wide.text
    # one tile of 2048^2 pixels: a render process would hold about 1.2 GB
    tile = dora.post("/jobs", json=dict(TINY, method="raster", width=2048, height=2048,
                                        tile_size=2048, progressive=False))
    assert tile.status_code == 422, tile.text
    assert tile.json()["detail"][0]["loc"] == ["body", "tile_size"]
    assert "RAYFARM_LIMITS_ARTIST__MAX_UNIT_BYTES" in tile.text and "tile_size <=" in tile.text
    # BDPT's every unit splats over the whole frame: the frame is what to shrink
    splats = dora.post("/jobs", json=dict(TINY, method="bdpt", width=4096, height=4096,
                                          tile_size=64))
    assert splats.status_code == 422, splats.text
    assert splats.json()["detail"][0]["loc"] == ["body", "width"]
    assert "RAYFARM_LIMITS_ARTIST__MAX_UNIT_BYTES" in splats.text
