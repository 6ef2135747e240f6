"""Resources of the farm: the renderer's cache under the data dir (cleared by
`rayfarm cache clear`), and a full disk that is visible and loses nothing."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import threading
from collections import namedtuple
from pathlib import Path

from fastapi.testclient import TestClient

from renderer import cache as renderer_cache
from service.main import create_app
from service.settings import Settings
from service.store import Store

from conftest import (ADMIN_HEADERS, TINY, TEST_ADMIN_TOKEN, assert_bit_identical, channels_of,
                      get_json, poll_job, rayfarm_command, submit, wait_for)

RADIOSITY = dict(TINY, method="radiosity", spp=1, depth=2, tile_size=16, progressive=False,
                 options={"patch_size": 0.5, "ff_rays": 16})


def _cli(env: dict, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*rayfarm_command(), *args], env=env, capture_output=True, text=True,
                          timeout=300)


def test01_the_service_caches_under_the_data_dir_and_cache_clear_empties_it(
        tmp_path, monkeypatch):
    home, data = tmp_path / "home", tmp_path / "data"
    home.mkdir()
    monkeypatch.delenv("RAYFARM_CACHE_DIR", raising=False)  # the tests' own override
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("XDG_CACHE_HOME", str(home / ".cache"))
    settings = Settings(data_dir=data, local_workers=1, poll_interval=0.05)
    assert settings.cache_dir == data / "cache"
    try:
        with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
            job = poll_job(get_json(client), submit(client, RADIOSITY)["id"])
            assert job["status"] == "done", job
    finally:
        renderer_cache.reset()
    entries = list((data / "cache" / "radiosity").glob("*.entry"))
    assert entries, "the radiosity solution must be cached under <data_dir>/cache"
    assert list(home.rglob("*")) == [], "nothing may be written under HOME"

    env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    env.update(RAYFARM_DATA_DIR=str(data), HOME=str(home))
    info = _cli(env, "cache", "info")
    assert info.returncode == 0, info.stderr
    assert f"radiosity: {len(entries)} entries" in info.stdout, info.stdout
    assert str(data / "cache" / "radiosity") in info.stdout
    cleared = _cli(env, "cache", "clear")
    assert cleared.returncode == 0, cleared.stderr
    assert list((data / "cache" / "radiosity").glob("*.entry")) == []
    assert "radiosity: 0 entries" in _cli(env, "cache", "info").stdout


def test02_a_full_disk_is_visible_and_loses_nothing(tmp_path, monkeypatch, reference_channels):
    full = threading.Event()
    full.set()
    refused: list[Path] = []
    write = Store._write_atomic

    def write_or_enospc(path, data, **kwargs):
        if full.is_set() and Path(path).suffix == ".film":
            refused.append(Path(path))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return write(path, data, **kwargs)

    monkeypatch.setattr(Store, "_write_atomic", staticmethod(write_or_enospc))
    settings = Settings(data_dir=tmp_path / "data", local_workers=1, poll_interval=0.05,
                        admin_token=TEST_ADMIN_TOKEN, min_free_bytes=1 << 20)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        health = client.get("/healthz").json()
        assert health["status"] == "ok" and health["disk"] == "ok", health
        assert health["disk_free_bytes"] > 0
        assert "data_dir" not in health  # public: no server paths

        job_id = submit(client, TINY)["id"]
        no_space = os.strerror(errno.ENOSPC)

        def stuck():
            job = client.get(f"/jobs/{job_id}").json()
            return job if job["error"] and no_space in job["error"] else None
        job = wait_for(stuck, 120, "the job to show the storage error")
        assert job["status"] == "running", job
        assert "storing the unit's film failed: No space left on device" in job["error"], job
        units = client.get(f"/jobs/{job_id}/units").json()
        waiting = [u for u in units if u["error"] and no_space in u["error"]]
        assert waiting and all(u["state"] != "done" for u in waiting), units
        assert job["progress"]["units_done"] == 0, job  # nothing stored, nothing done
        wait_for(lambda: len(refused) >= 3, 30, "the store to be retried on later ticks")
        assert client.get(f"/jobs/{job_id}").json()["progress"]["units_done"] == 0
        assert "scheduler_error" not in client.get("/healthz").json()

        # Low space on the data dir's file system: /healthz says so.
        usage = namedtuple("usage", "total used free")
        monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 << 30, 10 << 30, 4096))
        health = client.get("/healthz")
        assert health.status_code == 200
        assert health.json()["status"] == "degraded" and health.json()["disk"] == "low"
        assert health.json()["disk_free_bytes"] == 4096
        monkeypatch.undo()  # space is back (and the store writes again)
        monkeypatch.setattr(Store, "_write_atomic", staticmethod(write_or_enospc))
        full.clear()

        job = poll_job(get_json(client), job_id)
        assert job["status"] == "done" and job["error"] is None, job
        units = client.get(f"/jobs/{job_id}/units").json()
        assert all(u["error"] is None and u["state"] == "done" for u in units), units
        # The results that waited were kept, not thrown away and rendered again.
        assert all(u["tasks"] == 1 for u in units), units
        assert client.get("/healthz").json()["status"] == "ok"
        exr = tmp_path / "result.exr"
        exr.write_bytes(client.get(job["result_url"]).content)
    assert_bit_identical(channels_of(exr), reference_channels(TINY))


def test03_a_full_disk_while_writing_the_result_waits_instead_of_failing(
        tmp_path, monkeypatch, reference_channels):
    from service import results

    full = threading.Event()
    full.set()
    refused: list[str] = []
    write_exr = results.write_exr

    def write_or_enospc(path, *args, **kwargs):
        if full.is_set():
            refused.append(str(path))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return write_exr(path, *args, **kwargs)

    monkeypatch.setattr(results, "write_exr", write_or_enospc)
    settings = Settings(data_dir=tmp_path / "data", local_workers=1, poll_interval=0.05,
                        admin_token=TEST_ADMIN_TOKEN)
    with TestClient(create_app(settings), headers=ADMIN_HEADERS) as client:
        job_id = submit(client, TINY)["id"]

        def waiting():
            job = client.get(f"/jobs/{job_id}").json()
            return job if job["error"] else None
        job = wait_for(waiting, 120, "the job to show the result's storage error")
        assert job["status"] == "running", job
        assert job["error"] == "writing the result failed: No space left on device", job
        wait_for(lambda: len(refused) >= 3, 30, "the merge to be retried on later ticks")
        assert client.get(f"/jobs/{job_id}").json()["status"] == "running"
        full.clear()
        job = poll_job(get_json(client), job_id)
        assert job["status"] == "done" and job["error"] is None, job
        exr = tmp_path / "result.exr"
        exr.write_bytes(client.get(job["result_url"]).content)
    assert_bit_identical(channels_of(exr), reference_channels(TINY))
