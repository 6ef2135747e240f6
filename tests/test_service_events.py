"""Event streams, progress and ETA, job stats, the noise map, delete, and the
workers of the embedded pool: over the HTTP API of a real embedded service."""

from __future__ import annotations

import io
import json
import threading
import time

import numpy as np
import pytest
from PIL import Image

from renderer.film import NOISE_UNKNOWN, noise_srgb8, relative_error

from conftest import TINY, channels_of, get_json, poll_job, submit, wait_for

BIG = dict(TINY, width=256, height=256, spp=64, tile_size=16)  # seconds of work


def read_events(response, stop=lambda kind, data: kind == "end", limit: float = 300.0):
    """Parse a text/event-stream response into (kind, data) pairs until `stop`."""
    events, kind, data, deadline = [], None, [], time.monotonic() + limit
    for line in response.iter_lines():
        if time.monotonic() > deadline:
            pytest.fail(f"no end of the stream after {limit} s: {[k for k, _ in events]}")
        if line.startswith(":") or line.startswith("retry:") or line.startswith("id:"):
            continue
        if line.startswith("event:"):
            kind = line[len("event:"):].strip()
        elif line.startswith("data:"):
            data.append(line[len("data:"):].strip())
        elif line == "" and kind is not None:
            events.append((kind, json.loads("\n".join(data))))
            if stop(kind, events[-1][1]):
                return events
            kind, data = None, []
    return events


# Test01's job: sixteen units, long enough that the stream opens while it runs
# (TINY at 16 spp is 16384 samples, a few ms once warm: it could finish between
# the POST and the GET, and the stream saw only "done") and that the scheduler
# lands its units in several ticks. The ETA needs two landings before the last
# (Job.note_samples: the first only starts the measurement), and a tick
# collects every unit that landed since the one before, a poll_interval (50 ms
# here) apart, or up to four (Scheduler.PACE_SPAN) while both render processes
# have a unit waiting: at 256 spp the job took about 0.2 s on one machine and
# less on a faster one, whose ticks landed it in two batches, the second
# finishing the job, so no running job ever showed an ETA. At 1024 spp it
# takes about four times as many ticks.
STREAMED = dict(TINY, width=64, height=64, spp=1024, tile_size=16)


def test01_a_job_stream_carries_snapshot_units_previews_progress_and_end(local_client):
    job = submit(local_client, STREAMED)
    with local_client.stream("GET", f"/jobs/{job['id']}/events") as response:
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        events = read_events(response)
    kinds = [k for k, _ in events]
    assert kinds[0] == "job" and events[0][1]["id"] == job["id"]
    assert kinds[-1] == "end" and events[-1][1] == {"job_id": job["id"], "status": "done"}
    jobs = [d for k, d in events if k == "job"]
    assert [j["status"] for j in jobs][-1] == "done" and "running" in [j["status"] for j in jobs]
    # Progress only grows, ends at every sample, and an ETA was measured on the way.
    done = [j["progress"]["samples_done"] for j in jobs]
    assert done == sorted(done) and done[-1] == 64 * 64 * 1024 == jobs[-1]["progress"]["samples_total"]
    assert any(j["progress"]["eta"] and j["status"] == "running" for j in jobs)
    # Every unit is seen done, the done ones with their worker and time: in a unit
    # event, or in the stream's first `units` snapshot if it landed before the
    # stream began (its passes are a unit each: the first lands soon).
    snapshot = [u for k, d in events if k == "units" for u in d]  # pending ones too
    units = [d for k, d in events if k == "unit"]
    total = jobs[-1]["progress"]["units_total"]
    finished = {u["index"]: u for u in snapshot + units if u["state"] == "done"}
    assert len(finished) == total and {u["state"] for u in units} <= {"queued", "running", "done"}
    assert all(u["worker"] and u["seconds"] >= 0 and u.get("job_id", job["id"]) == job["id"]
               for u in finished.values())
    # The last preview event comes with the final merge; its images exist.
    previews = [d for k, d in events if k == "preview"]
    assert previews and previews[-1]["units"] == total
    assert [p["version"] for p in previews] == sorted(p["version"] for p in previews)
    for key in ("url", "noise_url"):
        image = local_client.get(previews[-1][key])
        assert image.status_code == 200 and image.headers["content-type"] == "image/png"


def test02_a_finished_job_stream_is_its_snapshot_and_end(local_client):
    job = poll_job(get_json(local_client), submit(local_client, TINY)["id"])
    with local_client.stream("GET", f"/jobs/{job['id']}/events") as response:
        events = read_events(response)
    assert [k for k, _ in events] == ["job", "units", "end"]
    assert len(events[1][1]) == job["progress"]["units_total"]
    assert all(u["state"] == "done" for u in events[1][1])
    assert local_client.get("/jobs/0123456789ab/events").status_code == 404


def test03_cancel_ends_the_stream_and_delete_removes_everything(local_client, local_settings):
    job = submit(local_client, BIG)
    with local_client.stream("GET", f"/jobs/{job['id']}/events") as response:
        # The running preview is written just after a landed unit is committed: wait
        # for the file itself, not the unit count, or the check below races it.
        wait_for(lambda: local_client.get(f"/jobs/{job['id']}/preview.png").status_code == 200,
                 300, "the first preview")
        canceled = local_client.post(f"/jobs/{job['id']}/cancel")
        assert canceled.status_code == 200 and canceled.json()["status"] == "canceled"
        events = read_events(response)
    assert events[-1] == ("end", {"job_id": job["id"], "status": "canceled"})
    assert local_client.post(f"/jobs/{job['id']}/cancel").status_code == 409
    job_dir = local_settings.data_dir / "jobs" / job["id"]
    assert (job_dir / "preview.png").is_file()
    # The GET of the running job's preview said someone is looking (service.previews).
    assert (job_dir / "preview.watched").is_file() and not (job_dir / "noise.watched").exists()
    assert local_client.delete(f"/jobs/{job['id']}").status_code == 204
    assert local_client.get(f"/jobs/{job['id']}").status_code == 404
    assert local_client.get(f"/jobs/{job['id']}/units").status_code == 404
    assert local_client.delete(f"/jobs/{job['id']}").status_code == 404
    assert not job_dir.exists()
    assert job["id"] not in [j["id"] for j in local_client.get("/jobs").json()]


def test04_deleting_a_running_job_cancels_it_and_its_stream_ends(local_client, local_settings):
    job = submit(local_client, BIG)
    with local_client.stream("GET", f"/jobs/{job['id']}/events") as response:
        wait_for(lambda: get_json(local_client)(f"/jobs/{job['id']}")["status"] == "running",
                 300, "the job to run")
        assert local_client.delete(f"/jobs/{job['id']}").status_code == 204
        events = read_events(response)
    assert events[-1] == ("end", {"job_id": job["id"], "status": "deleted"})
    assert ("deleted", {"job_id": job["id"]}) in events
    time.sleep(0.5)  # ten scheduler ticks: units in flight land and are dropped again
    assert not (local_settings.data_dir / "jobs" / job["id"]).exists()
    assert local_client.get("/healthz").json()["status"] == "ok"


def test05_the_stream_of_every_job_sees_new_jobs_progress_and_deletions(local_client):
    seen: list[tuple[str, dict]] = []
    with local_client.stream("GET", "/events") as response:
        job = submit(local_client, TINY)

        def reader():
            read_events(response, stop=lambda kind, data: seen.append((kind, data)) or (
                kind == "deleted" and data["job_id"] == job["id"]), limit=300)
        thread = threading.Thread(target=reader, daemon=True)
        thread.start()
        poll_job(get_json(local_client), job["id"])
        assert local_client.delete(f"/jobs/{job['id']}").status_code == 204
        thread.join(60)
    mine = [(k, d) for k, d in seen if d.get("id", d.get("job_id")) == job["id"]]
    assert {k for k, _ in seen} <= {"job", "deleted", "resync"}  # no unit or preview chatter
    statuses = [d["status"] for k, d in mine if k == "job"]
    assert statuses[0] == "queued" and "running" in statuses and statuses[-1] == "done"
    assert mine[-1] == ("deleted", {"job_id": job["id"]})


def test06_noise_map_is_the_relative_error_of_the_exr(local_client, tmp_path):
    job = poll_job(get_json(local_client), submit(local_client, dict(TINY, spp=8))["id"])
    exr = tmp_path / "noise.exr"
    exr.write_bytes(local_client.get(job["result_url"]).content)
    ch = channels_of(exr)
    mean = np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float64)
    var = np.stack([ch["var.R"], ch["var.G"], ch["var.B"]], -1).astype(np.float64)
    response = local_client.get(job["noise_url"])
    assert response.status_code == 200
    png = np.asarray(Image.open(io.BytesIO(response.content)).convert("RGB")).astype(int)
    # The EXR holds float32 mean and variance: one 8-bit step of difference at most.
    assert np.abs(png - noise_srgb8(mean, var).astype(int)).max() <= 1
    assert len(np.unique(png.reshape(-1, 3), axis=0)) > 10  # a map, not a flat colour


def test07_relative_error_and_its_colours():
    mean = np.array([[[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.2, 0.2, 0.2]]])
    var = np.array([[[0.0025] * 3, [0.0] * 3, [1.0] * 3, [np.inf] * 3]])
    err = relative_error(mean, var)
    assert err[0, 0] == pytest.approx(0.1) and err[0, 1] == 0.0 and err[0, 2] == 1.0
    assert np.isinf(err[0, 3])
    rgb = noise_srgb8(mean, var)
    assert tuple(rgb[0, 1]) == (0, 0, 4) and tuple(rgb[0, 2]) == (252, 255, 164)  # the ends
    assert tuple(rgb[0, 3]) == NOISE_UNKNOWN
    # Ten times the error is a third of the log range brighter: the map is monotone.
    assert rgb[0, 0].sum() > rgb[0, 1].sum() and rgb[0, 2].sum() > rgb[0, 0].sum()


def test08_stats_and_the_local_worker(local_client):
    get = get_json(local_client)
    job = poll_job(get, submit(local_client, dict(TINY, seed=11))["id"])
    stats, progress = job["stats"], job["progress"]
    assert stats["samples_per_second"] == pytest.approx(job["samples"] / progress["elapsed"])
    assert stats["rays_per_second"] == pytest.approx(job["rays"] / progress["elapsed"])
    units = get(f"/jobs/{job['id']}/units")
    assert stats["seconds_per_unit"] == pytest.approx(
        sum(u["seconds"] for u in units) / len(units))
    assert stats["units_retried"] == 0 == sum(u["tasks"] > 1 for u in units)
    workers = get("/workers")
    assert len(workers) == 1
    pool = workers[0]
    assert pool["kind"] == "local" and pool["concurrency"] == 2 and pool["state"] in ("idle", "busy")
    assert pool["name"] == units[0]["worker"]
    assert pool["units_done"] >= len(units) and pool["samples"] >= job["samples"]
    assert pool["samples_per_second"] == pytest.approx(pool["samples"] / pool["seconds"])
    # While a big job renders, the pool shows exactly the units its processes render.
    big = submit(local_client, BIG)

    def rendering():
        w = get("/workers")[0]
        return w if w["state"] == "busy" and any(r["job_id"] == big["id"] for r in w["running"]) \
            else None
    busy = wait_for(rendering, 300, "the pool to render the big job")
    assert 1 <= len(busy["running"]) <= 2
    assert local_client.post(f"/jobs/{big['id']}/cancel").status_code == 200
