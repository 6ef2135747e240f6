"""Admission control (service.admission): per-role limits on one job, on an
owner's active jobs, and sliding-window rates, with the 429's Retry-After."""

from __future__ import annotations

import threading
from dataclasses import replace
from datetime import timedelta

import pytest

from renderer import RenderSpec
from service import admission
from service.access import Principal
from service.admission import (RateLimiter, check_job, check_memory, count_active_jobs,
                               limits_for)
from service.db import open_ledger
from service.errors import Forbidden, InvalidRequest, RateLimited
from service.models import Job, utcnow
from service.settings import Settings

ANA = Principal("ana", "artist", token_id="a1")
ROOT = Principal("root", "admin", token_id="r1")
VERA = Principal("vera", "viewer", token_id="v1")


@pytest.fixture
def settings(tmp_path, monkeypatch):
    monkeypatch.setenv("RAYFARM_LIMITS_ARTIST__MAX_SAMPLES_PER_JOB", "100000")
    monkeypatch.setenv("RAYFARM_LIMITS_ARTIST__MAX_UNITS_PER_JOB", "64")
    monkeypatch.setenv("RAYFARM_LIMITS_ARTIST__MAX_ACTIVE_JOBS", "2")
    monkeypatch.setenv("RAYFARM_LIMITS_ARTIST__SUBMISSIONS_PER_MINUTE", "3")
    monkeypatch.setenv("RAYFARM_LIMITS_ARTIST__UPLOADS_PER_HOUR", "2")
    return Settings(data_dir=tmp_path / "data")


def spec(**fields) -> RenderSpec:
    return RenderSpec(**{"method": "path", "spp": 16, "depth": 3, "width": 64, "height": 64,
                         "tile_size": 16, **fields}).validate()


def test01_limits_follow_the_role_and_a_viewer_submits_nothing(settings):
    assert limits_for(settings, ANA).max_samples_per_job == 100000  # from the environment
    assert limits_for(settings, ROOT) is settings.limits_admin
    assert limits_for(settings, ROOT).max_active_jobs == 1000
    with pytest.raises(Forbidden, match="viewer"):
        limits_for(settings, VERA)
    with pytest.raises(Forbidden):
        check_job(settings, VERA, spec(), units=1, active_jobs=0)


def test02_too_many_samples_names_spp_the_limit_and_its_setting(settings):
    check_job(settings, ANA, spec(spp=24), units=16, active_jobs=0)  # 98304 samples: fine
    with pytest.raises(InvalidRequest) as refused:
        check_job(settings, ANA, spec(spp=25), units=16, active_jobs=0)  # 102400
    assert refused.value.field == "spp"
    message = str(refused.value)
    assert "100000" in message and "102400" in message
    assert "RAYFARM_LIMITS_ARTIST__MAX_SAMPLES_PER_JOB" in message
    assert "spp <= 24" in message
    check_job(settings, ROOT, spec(spp=25), units=16, active_jobs=0)  # an admin's cap is higher


def test03_too_many_units_names_tile_size(settings):
    body = spec(spp=4, tile_size=4)  # 16 x 16 tiles
    units = admission.planned_units(body, progressive=False)
    assert units == 256
    # progressive: passes of 1, 1 and 2 spp, each a single unit (the whole 64 x 64
    # frame holds fewer than MIN_UNIT_SAMPLES samples), counted exactly unplanned
    assert admission.planned_units(body, progressive=True) == 3
    assert admission.unit_floor(body, progressive=True) == 3
    assert admission.unit_floor(body, progressive=False) == units
    check_job(settings, ANA, spec(spp=4), units=admission.planned_units(spec(spp=4), False),
              active_jobs=0)
    with pytest.raises(InvalidRequest) as refused:
        check_job(settings, ANA, body, units=units, active_jobs=0)
    assert refused.value.field == "tile_size"
    assert "256" in str(refused.value) and "RAYFARM_LIMITS_ARTIST__MAX_UNITS_PER_JOB" in str(
        refused.value)


def test04_too_many_active_jobs_is_rate_limited(settings):
    check_job(settings, ANA, spec(), units=16, active_jobs=1)
    with pytest.raises(RateLimited) as refused:
        check_job(settings, ANA, spec(), units=16, active_jobs=2)
    assert refused.value.retry_after == admission.ACTIVE_JOBS_RETRY_AFTER > 0
    assert "RAYFARM_LIMITS_ARTIST__MAX_ACTIVE_JOBS" in str(refused.value)


def test05_active_jobs_are_the_owners_queued_running_and_paused_ones(settings):
    engine, sessions = open_ledger(settings)
    try:
        now = utcnow()
        with sessions.begin() as session:
            for i, (owner, status) in enumerate([("ana", "queued"), ("ana", "running"),
                                                 ("ana", "paused"), ("ana", "done"),
                                                 ("ana", "failed"), ("ana", "canceled"),
                                                 ("ben", "running")]):
                session.add(Job(id=f"job{i}", created=now + timedelta(seconds=i), status=status,
                                owner=owner, scene="cornell-box", scene_hash="0" * 64, spec={},
                                width=8, height=8))
        with sessions() as session:
            assert count_active_jobs(session, "ana") == 3
            assert count_active_jobs(session, "ben") == 1
            assert count_active_jobs(session, "cleo") == 0
    finally:
        engine.dispose()


def test06_the_sliding_window_refuses_with_the_seconds_until_the_oldest_hit_leaves():
    limiter = RateLimiter()
    for t in (100.0, 110.0, 130.0):
        limiter.hit("k", limit=3, window_seconds=60, now=t)
    with pytest.raises(RateLimited) as refused:
        limiter.hit("k", limit=3, window_seconds=60, now=135.0)
    assert refused.value.retry_after == pytest.approx(25.0)  # the hit at 100 leaves at 160
    with pytest.raises(RateLimited) as refused:  # a refused hit is not recorded
        limiter.hit("k", limit=3, window_seconds=60, now=159.5)
    assert refused.value.retry_after == pytest.approx(0.5)
    limiter.hit("k", limit=3, window_seconds=60, now=160.0)  # exactly when it said
    with pytest.raises(RateLimited) as refused:
        limiter.hit("k", limit=3, window_seconds=60, now=161.0)
    assert refused.value.retry_after == pytest.approx(9.0)  # next: the hit at 110
    limiter.hit("other", limit=3, window_seconds=60, now=161.0)  # keys are apart
    with pytest.raises(RateLimited) as refused:
        limiter.hit("none", limit=0, window_seconds=60, now=0.0)
    assert refused.value.retry_after == 60


def test07_the_limiter_is_thread_safe():
    limiter = RateLimiter()
    admitted, refused = [], []
    start = threading.Barrier(8)

    def client():
        start.wait()
        for _ in range(50):
            try:
                limiter.hit("k", limit=100, window_seconds=3600)
                admitted.append(1)
            except RateLimited:
                refused.append(1)
    threads = [threading.Thread(target=client) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(admitted) == 100 and len(refused) == 300


def test08_submissions_per_token_and_minute_uploads_per_owner_and_hour(settings):
    limiter = RateLimiter()
    for t in (0.0, 1.0, 2.0):
        admission.check_submission_rate(limiter, settings, ANA, now=t)
    with pytest.raises(RateLimited) as refused:
        admission.check_submission_rate(limiter, settings, ANA, now=3.0)
    assert refused.value.retry_after == pytest.approx(57.0)
    # Another token of the same user has its own budget; an admin has 600 a minute.
    admission.check_submission_rate(limiter, settings, Principal("ana", "artist", "a2"), now=3.0)
    for t in range(10):
        admission.check_submission_rate(limiter, settings, ROOT, now=float(t))
    # Uploads count per owner, whatever the token, within an hour.
    admission.check_upload_rate(limiter, settings, ANA, now=0.0)
    admission.check_upload_rate(limiter, settings, Principal("ana", "artist", "a2"), now=600.0)
    with pytest.raises(RateLimited) as refused:
        admission.check_upload_rate(limiter, settings, ANA, now=1200.0)
    assert refused.value.retry_after == pytest.approx(2400.0)
    with pytest.raises(Forbidden):
        admission.check_upload_rate(limiter, settings, VERA, now=0.0)


def test08b_an_experiment_counts_a_submission_per_job(settings):
    """Many hits at once fit or are refused whole, with the seconds until
    enough leave the window; more than the limit could never fit (422)."""
    limiter = RateLimiter()
    admission.check_submission_rate(limiter, settings, ANA, now=0.0)
    admission.check_submission_rate(limiter, settings, ANA, now=10.0, jobs=2)
    with pytest.raises(RateLimited) as refused:  # full: 2 places must free up
        admission.check_submission_rate(limiter, settings, ANA, now=20.0, jobs=2)
    assert refused.value.retry_after == pytest.approx(50.0)  # the hits at 10 leave at 70
    admission.check_submission_rate(limiter, settings, ANA, now=60.0)  # the one at 0 left
    with pytest.raises(InvalidRequest) as too_many:
        admission.check_submission_rate(limiter, settings, ANA, now=0.0, jobs=4,
                                        field="repeats")
    assert too_many.value.field == "repeats" and "creates 4 jobs" in too_many.value.message
    assert "RAYFARM_LIMITS_ARTIST__SUBMISSIONS_PER_MINUTE" in too_many.value.message
    limiter.hit("k", limit=3, window_seconds=60, now=0.0, count=3)
    with pytest.raises(RateLimited) as refused:
        limiter.hit("k", limit=3, window_seconds=60, now=1.0)
    assert refused.value.retry_after == pytest.approx(59.0)


def test09_the_429_carries_retry_after_rounded_up(settings):
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from service.api.errors import install_error_handlers

    app = FastAPI()
    install_error_handlers(app)
    limiter, clock = RateLimiter(), {"now": 0.0}

    @app.post("/jobs")
    def post():
        limiter.hit("k", limit=1, window_seconds=60, now=clock["now"])
        return {}
    with TestClient(app) as client:
        assert client.post("/jobs").status_code == 200
        clock["now"] = 12.5
        response = client.post("/jobs")
    assert response.status_code == 429
    assert response.headers["retry-after"] == "48"  # 47.5 s, rounded up


@pytest.mark.parametrize("progressive", [True, False])
def test_unit_floor_is_a_lower_bound_of_every_methods_plan(progressive):
    """The floor refuses before planning; above the real count it would refuse
    jobs the limit admits (exact for tile plans)."""
    from renderer import METHODS, RenderSpec
    from service.admission import planned_units, unit_floor

    for name in dict.fromkeys(m.name for m in METHODS.values()):
        for spp, size in ((1, 8), (64, 48), (1000, 16)):
            spec = RenderSpec(method=name, spp=spp, width=size, height=size, tile_size=16)
            floor, units = unit_floor(spec, progressive), planned_units(spec, progressive)
            assert 1 <= floor <= units, (name, spp, size, floor, units)
            if METHODS[name].family == "tile":
                assert floor == units, name


# Jobs whose plans are large for their floor: BDPT's small passes, a photon
# job with a gather unit per tile and iteration, a photon map of many ranges.
_LARGE_PLANS = [
    dict(method="path", spp=64, width=512, height=512, tile_size=8),
    dict(method="bdpt", spp=64, width=256, height=256, tile_size=8),
    dict(method="radiosity", spp=4, width=256, height=256, tile_size=8),
    dict(method="photon", spp=128, width=128, height=128, tile_size=8,
         options={"iterations_per_unit": 1}),
    dict(method="photon", spp=16, width=64, height=64, tile_size=8,
         options={"mode": "photonmap", "photons": 1 << 24}),
]


def test10_planned_units_counts_a_plan_without_building_its_units(monkeypatch):
    """Admission counts a job's units in the request; building a plan of a
    few hundred thousand units there held the GIL for seconds (a photon job
    of one iteration per gather unit: millions). Every unit the planners
    would make goes through these classes: none is made."""
    import dataclasses
    import importlib

    from renderer.integrators import photon, radiosity
    from service.admission import job_plan, planned_units

    specs = [(RenderSpec(**body).validate(1 << 40), progressive) for body in _LARGE_PLANS
             for progressive in (False, True)]
    exact = [len(job_plan(spec, progressive)) for spec, progressive in specs]
    built = []

    def counted(cls):
        def make(*args, **kwargs):
            built.append(1)
            return cls(*args, **kwargs)
        return make
    for module in (importlib.import_module("renderer.plan"), photon, radiosity):
        monkeypatch.setattr(module, "Unit", counted(module.Unit))
    monkeypatch.setattr(radiosity, "replace", counted(dataclasses.replace))
    assert [planned_units(spec, progressive) for spec, progressive in specs] == exact
    assert not built, f"{len(built)} units built to count {sum(exact)}"


def test11_a_frame_above_the_artists_pixels_is_422_on_width_naming_the_setting(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", local_workers=2)  # the artist defaults
    body = dict(method="path-mis", spp=1, depth=3, tile_size=64)
    check_memory(settings, ANA, RenderSpec(width=4096, height=4096, **body), False)
    for width, height, field in ((4097, 4096, "width"), (4096, 4097, "height")):
        with pytest.raises(InvalidRequest) as refused:
            check_memory(settings, ANA, RenderSpec(width=width, height=height, **body), False)
        assert refused.value.field == field
        message = str(refused.value)
        assert "RAYFARM_LIMITS_ARTIST__MAX_PIXELS_PER_JOB" in message and "16777216" in message
    # an admin's frame may be as large as a frame can be
    check_memory(settings, ROOT, RenderSpec(width=8192, height=8192, **body), False)


def test12_a_unit_above_the_artists_bytes_is_422_on_tile_size_with_one_that_fits(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", local_workers=2)
    one_tile = RenderSpec(method="raster", spp=1, depth=3, width=2048, height=2048,
                          tile_size=2048)  # its film alone is 470 MB, its render 1.2 GB
    with pytest.raises(InvalidRequest) as refused:
        check_memory(settings, ANA, one_tile, False)
    assert refused.value.field == "tile_size"
    message = str(refused.value)
    assert "RAYFARM_LIMITS_ARTIST__MAX_UNIT_BYTES" in message
    tile = int(message.rsplit("tile_size <= ", 1)[1])
    assert 1024 <= tile < 2048
    assert check_memory(settings, ANA, replace(one_tile, tile_size=tile), False).unit <= 1 << 30
    with pytest.raises(InvalidRequest):
        check_memory(settings, ANA, replace(one_tile, tile_size=tile + 1), False)
    check_memory(settings, ROOT, one_tile, False)  # an admin's unit may hold 4 GiB


def test13_whole_frame_splats_above_the_unit_bytes_are_422_on_the_frame(tmp_path):
    """BDPT's every tile unit carries a splat batch over the whole frame, so a
    smaller tile does not help: the refusal names the frame."""
    settings = Settings(data_dir=tmp_path / "data", local_workers=2)
    for method in ("bdpt", "light", "mlt"):
        spec = RenderSpec(method=method, spp=1, depth=3, width=4096, height=4096, tile_size=16)
        with pytest.raises(InvalidRequest) as refused:
            check_memory(settings, ANA, spec, False)
        assert refused.value.field == "width", method
        assert "RAYFARM_LIMITS_ARTIST__MAX_UNIT_BYTES" in str(refused.value)
        assert "whole frame" in str(refused.value)
        # (larger tiles: BDPT's 16-pixel ones would store the frame's splats 4096 times)
        check_memory(settings, ANA, replace(spec, width=1024, height=1024, tile_size=256), False)


def test14_a_job_above_the_artists_bytes_with_every_process_is_422_naming_the_setting(tmp_path):
    """A unit in each of 16 render processes and the films they land in the
    service: 6.4 GB for 1024^2-pixel tiles, above the 6 GiB of an artist's job."""
    settings = Settings(data_dir=tmp_path / "data", local_workers=16)
    spec = RenderSpec(method="raster", spp=1, depth=3, width=4096, height=4096, tile_size=1024)
    with pytest.raises(InvalidRequest) as refused:
        check_memory(settings, ANA, spec, False)
    assert refused.value.field == "tile_size"
    message = str(refused.value)
    assert "RAYFARM_LIMITS_ARTIST__MAX_JOB_BYTES" in message and "16 render processes" in message
    tile = int(message.rsplit("tile_size <= ", 1)[1])
    check_memory(settings, ANA, replace(spec, tile_size=tile), False)
    check_memory(Settings(data_dir=tmp_path / "data", local_workers=2), ANA, spec, False)


def test15_a_job_whose_films_would_fill_the_store_is_422_naming_the_setting(tmp_path):
    """Unit films stay in the store until their job is deleted. BDPT stores the
    frame's splats with every tile of every pass: 2048^2 pixels in 64-pixel
    tiles are about 1 TB of films; the refusal names tile_size and the
    smallest tile that fits."""
    settings = Settings(data_dir=tmp_path / "data", local_workers=2)
    spec = RenderSpec(method="bdpt", spp=16, depth=5, width=2048, height=2048, tile_size=64)
    with pytest.raises(InvalidRequest) as refused:
        check_memory(settings, ANA, spec, True)
    assert refused.value.field == "tile_size"
    message = str(refused.value)
    assert "RAYFARM_LIMITS_ARTIST__MAX_JOB_STORE_BYTES" in message
    tile = int(message.rsplit("tile_size >= ", 1)[1])
    fits = check_memory(settings, ANA, replace(spec, tile_size=tile), True)
    assert fits.stored <= settings.limits_artist.max_job_store_bytes
    with pytest.raises(InvalidRequest):
        check_memory(settings, ANA, replace(spec, tile_size=tile - 1), True)
    # the artist's largest path-traced frame at the most samples stores less
    big = RenderSpec(method="path-mis", spp=64, depth=5, width=4096, height=4096, tile_size=64)
    assert check_memory(settings, ANA, big, True).stored <= 16 << 30
