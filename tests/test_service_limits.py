"""Admission through the API: the role's limits refuse a job too big (samples,
units: 422 naming the field and the setting), an owner with too many active
jobs (429), a token submitting too fast and an owner uploading too often (429
with Retry-After). Its own small farm with low artist limits. And request
bodies on a real server: a 2 GiB body to any route is refused unread (413),
a stranger's is not read at all (401), and every route has a limit."""

from __future__ import annotations

import select
import socket

import httpx
import pytest
from fastapi.testclient import TestClient

from conftest import ADMIN_HEADERS, TEST_ADMIN_TOKEN, TINY, embedded_env, start_serve
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


# -- request bodies, on a real server ----------------------------------------------------------

def _answer(sock: socket.socket) -> bytes:
    """The status line and headers of the server's answer (up to 60 s to come)."""
    sock.settimeout(60)
    answer = b""
    while b"\r\n\r\n" not in answer:
        data = sock.recv(4096)
        if not data:
            break
        answer += data
    return answer


def _send_chunked(sock: socket.socket, cap: int, start: bytes) -> tuple[int, bytes]:
    """Send a chunked body, `start` then spaces, until the server answers (or
    `cap` bytes went): (bytes sent, the answer)."""
    sent, chunk = 0, b" " * (64 << 10)
    frame = f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
    try:
        sock.sendall(f"{len(start):x}\r\n".encode() + start + b"\r\n")
        while sent < cap:
            if select.select([sock], [], [], 0)[0]:
                break  # the server answered (or closed) before the body was whole
            sock.sendall(frame)
            sent += len(chunk)
        else:
            sock.sendall(b"0\r\n\r\n")
    except OSError:  # the server closed the connection: it read no more
        pass
    return sent, _answer(sock)


PART = b'--b\r\nContent-Disposition: form-data; name="scene"; filename="room.json"\r\n\r\n'


def test04_a_huge_body_to_any_kind_of_route_is_refused_unread_or_at_its_limit(tmp_path):
    env = embedded_env(tmp_path / "data", RAYFARM_LOCAL_WORKERS="1",
                       RAYFARM_MAX_JOB_BYTES=str(1 << 20), RAYFARM_MAX_UPLOAD_BYTES=str(1 << 20))
    child, base = start_serve(env, tmp_path / "serve.log")
    host, port = base.removeprefix("http://").split(":")
    routes = [("POST", "/auth/login"), ("POST", "/experiments"), ("POST", "/users"),
              ("PATCH", "/jobs/0123456789ab"), ("POST", "/jobs/0123456789ab/cancel"),
              ("POST", "/tokens"), ("POST", "/jobs"), ("POST", "/scenes")]
    bearer = f"Authorization: Bearer {TEST_ADMIN_TOKEN}\r\n"
    # Offered chunked; what was sent is bounded by the route's limit plus the
    # kernel's socket buffers (a few MB on loopback), far below this.
    cap = 64 << 20
    try:
        for method, path in routes:
            for who in ("", bearer):
                kind = ("multipart/form-data; boundary=b" if path == "/scenes"
                        else "application/json")
                head = (f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n{who}"
                        f"Content-Type: {kind}\r\n").encode()
                # 2 GiB declared: answered at once, before a byte of the body was sent.
                with socket.create_connection((host, int(port))) as sock:
                    sock.sendall(head + f"Content-Length: {2 << 30}\r\n\r\n".encode())
                    answer = _answer(sock)
                    assert answer.startswith(b"HTTP/1.1 413"), (method, path, who, answer)
                # Chunked, no Content-Length: a stranger's body to a route that needs a
                # caller is not read at all; any other stops at the route's limit (or is
                # not read by a route that takes none: a job action's 404 here).
                with socket.create_connection((host, int(port))) as sock:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 256 << 10)
                    sock.sendall(head + b"Transfer-Encoding: chunked\r\n\r\n")
                    sent, answer = _send_chunked(sock, cap, PART if path == "/scenes" else b"[")
                status = int(answer.split()[1]) if answer else None
                if who or (method, path) == ("POST", "/auth/login"):
                    expected = 404 if path.endswith("/cancel") else 413
                    assert status == expected and sent < cap // 4, (method, path, who, sent)
                else:
                    assert status == 401 and sent < cap // 4, (method, path, sent, answer)
        with httpx.Client(base_url=base, headers=ADMIN_HEADERS, timeout=60) as client:
            # A small route's limit is named, and counts for every job (a path template).
            refused = client.patch("/jobs/fedcba987654", content=b" " * (65 << 10))
            assert refused.status_code == 413, refused.text
            assert "RAYFARM_MAX_BODY_BYTES" in refused.json()["detail"]
            assert client.get("/healthz").status_code == 200
    finally:
        child.stop()
    assert "Traceback" not in child.log(), child.log()


def test05_a_frame_too_big_to_hold_is_422_naming_the_field_and_the_setting(farm):
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
