"""GET /jobs/{id}/pixels: a job's image as float32 data for the HDR viewer
(service.pixels) — the EXR's own values, layer by layer, for a done job, the
merged frame so far for a running one, the finished units for a canceled one."""

from __future__ import annotations

import numpy as np

from conftest import TINY, poll_job, get_json, submit, wait_for


def pixels(client, job_id: str, layer: str = "beauty") -> tuple[np.ndarray, dict]:
    response = client.get(f"/jobs/{job_id}/pixels", params={"layer": layer})
    assert response.status_code == 200, response.text
    head = response.headers
    assert head["content-type"] == "application/octet-stream"
    shape = (int(head["x-image-height"]), int(head["x-image-width"]),
             len(head["x-image-channels"].split(",")))
    data = np.frombuffer(response.content, dtype="<f4").reshape(shape)
    return data, head


def exr_channels(client, job_id: str, tmp_path) -> dict[str, np.ndarray]:
    from renderer import read_exr

    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.get(f"/jobs/{job_id}/result.exr").content)
    return read_exr(path)[0]


def test01_a_done_jobs_layers_are_its_exrs_values_bit_for_bit(local_client, tmp_path):
    body = dict(TINY, width=24, height=16, spp=8)
    job = poll_job(get_json(local_client), submit(local_client, body)["id"])
    assert job["status"] == "done"
    exr = exr_channels(local_client, job["id"], tmp_path)
    beauty, head = pixels(local_client, job["id"])
    assert head["x-image-source"] == "final" and head["x-image-channels"] == "R,G,B"
    layers = head["x-image-layers"].split(",")
    assert {"beauty", "var", "samples", "albedo", "normal", "depth"} <= set(layers)
    assert beauty.shape == (16, 24, 3)
    for i, name in enumerate("RGB"):
        assert np.array_equal(beauty[..., i], exr[name])  # not quantized, not tonemapped
    var, head = pixels(local_client, job["id"], "var")
    assert head["x-image-channels"] == "var.R,var.G,var.B"
    assert np.array_equal(var[..., 1], exr["var.G"])
    normal, head = pixels(local_client, job["id"], "normal")
    assert head["x-image-channels"] == "normal.X,normal.Y,normal.Z"
    samples, _ = pixels(local_client, job["id"], "samples")
    assert samples.shape == (16, 24, 1) and (samples == 8).all()


def test02_a_missing_layer_is_a_422_naming_those_there_are(local_client):
    job = poll_job(get_json(local_client), submit(local_client, dict(TINY, width=8, height=8))["id"])
    response = local_client.get(f"/jobs/{job['id']}/pixels", params={"layer": "denoised"})
    assert response.status_code == 422
    detail = str(response.json()["detail"])
    assert "denoised" in detail and "beauty" in detail and "var" in detail
    assert local_client.get("/jobs/0123456789ab/pixels").status_code == 404


def test03_running_then_canceled_the_pixels_are_what_landed(local_client, tmp_path):
    body = dict(TINY, width=64, height=64, spp=512, tile_size=8, progressive=False)  # 64 units
    job_id = submit(local_client, body)["id"]
    # Running: the frame merged so far (written with the preview once fetched).
    def running():
        response = local_client.get(f"/jobs/{job_id}/pixels", params={"layer": "samples"})
        return response.status_code == 200 and response.headers["x-image-source"] == "running"
    wait_for(running, 120, "a running job's pixels")
    samples, _ = pixels(local_client, job_id, "samples")
    tiles = samples[..., 0].reshape(8, 8, 8, 8).max(axis=(1, 3))
    assert set(np.unique(tiles)) <= {0.0, 512.0} and (tiles == 512).sum() >= 1
    canceled = local_client.post(f"/jobs/{job_id}/cancel").json()
    assert canceled["status"] == "canceled"
    beauty, head = pixels(local_client, job_id)
    assert head["x-image-source"] == "partial"
    exr = exr_channels(local_client, job_id, tmp_path)  # the partial EXR
    assert np.array_equal(beauty[..., 0], exr["R"])
