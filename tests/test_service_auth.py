"""Accounts: every route needs a caller; artists are isolated from each other;
viewers read and change nothing; tokens are random, hashed, revocable and
expire; the dashboard's cookie login, its CSRF check, the security headers,
CORS off by default, the first admin and the admin CLI.

Runs on the session's embedded service (`local_client`, logged in as admin)
with users made by `make_user`.
"""

from __future__ import annotations

import os
import re
import socket
import sqlite3
import stat
import subprocess
import threading
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient

from conftest import (ADMIN_HEADERS, TEST_ADMIN_TOKEN, TINY, get_json, poll_job, rayfarm_command,
                      submit, wait_for)
from service import auth
from service.access import Principal
from service.models import ApiToken, User, utcnow

from test_service_events import read_events

PUBLIC = {("GET", "/healthz"), ("GET", "/metrics"), ("GET", "/"), ("POST", "/auth/login"),
          ("GET", "/docs"), ("GET", "/redoc")}


def _concrete(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "0123456789ab", path)


def test01_every_route_but_the_public_ones_answers_401_without_a_token(local_app, local_client):
    schema = local_client.get("/openapi.json").json()
    anonymous = TestClient(local_app)
    assert anonymous.get("/openapi.json").status_code == 401
    checked = 0
    for path, operations in schema["paths"].items():
        for method in operations:
            if (method.upper(), path) in PUBLIC:
                continue
            response = anonymous.request(method.upper(), _concrete(path))
            assert response.status_code == 401, (method, path, response.status_code)
            assert response.headers["www-authenticate"].startswith("Bearer")
            # The schema documents it.
            assert "401" in operations[method]["responses"], (method, path)
            checked += 1
    assert checked >= 25
    for bad in ("Bearer", "Bearer nope", "Basic YWRtaW46YWRtaW4=", "Bearer " + "x" * 500):
        assert anonymous.get("/jobs", headers={"Authorization": bad}).status_code == 401
    assert anonymous.get("/healthz").status_code == 200
    assert anonymous.get("/metrics").status_code == 200
    assert anonymous.get("/static/app.css").status_code == 200


def test02_an_artist_cannot_see_change_or_stream_another_artists_job(local_client, make_user):
    ana, bob = make_user("ana"), make_user("bob")
    job = submit(ana, TINY)
    assert job["owner"] == "ana"
    jid = job["id"]
    for method, path in (("GET", f"/jobs/{jid}"), ("GET", f"/jobs/{jid}/units"),
                         ("GET", f"/jobs/{jid}/events"), ("GET", f"/jobs/{jid}/preview.png"),
                         ("GET", f"/jobs/{jid}/result.exr"), ("POST", f"/jobs/{jid}/cancel"),
                         ("POST", f"/jobs/{jid}/pause"), ("POST", f"/jobs/{jid}/requeue"),
                         ("PATCH", f"/jobs/{jid}"), ("DELETE", f"/jobs/{jid}")):
        kwargs = {"json": {"priority": 5}} if method == "PATCH" else {}
        response = bob.request(method, path, **kwargs)
        assert response.status_code == 404, (method, path, response.status_code)
        assert response.json() == {"detail": f"no job '{jid}'"}  # as for a job that never was
    assert jid not in {j["id"] for j in bob.get("/jobs").json()}
    assert jid in {j["id"] for j in ana.get("/jobs").json()}
    assert jid in {j["id"] for j in local_client.get("/jobs").json()}  # the admin sees all
    done = poll_job(get_json(ana), jid)
    assert done["status"] == "done"
    assert ana.get(f"/jobs/{jid}/result.exr").status_code == 200
    assert bob.delete(f"/jobs/{jid}").status_code == 404
    assert ana.get(f"/jobs/{jid}").json()["status"] == "done"  # untouched by bob's tries
    assert ana.delete(f"/jobs/{jid}").status_code == 204


def test03_the_stream_of_every_job_carries_only_the_callers_jobs(make_user):
    cleo, dan = make_user("cleo"), make_user("dan")
    seen: list[tuple[str, dict]] = []
    with dan.stream("GET", "/events") as response:
        other = submit(cleo, TINY)
        mine = submit(dan, TINY)

        def reader():
            read_events(response, stop=lambda kind, data: seen.append((kind, data)) or (
                kind == "deleted" and data["job_id"] == mine["id"]), limit=300)
        thread = threading.Thread(target=reader, daemon=True)
        thread.start()
        poll_job(get_json(cleo), other["id"])
        poll_job(get_json(dan), mine["id"])
        assert cleo.delete(f"/jobs/{other['id']}").status_code == 204
        assert dan.delete(f"/jobs/{mine['id']}").status_code == 204
        thread.join(60)
    ids = {d.get("id", d.get("job_id")) for _, d in seen}
    assert mine["id"] in ids and ("deleted", {"job_id": mine["id"]}) in seen
    assert other["id"] not in ids


def test04_a_viewer_reads_everything_and_changes_nothing(local_client, make_user):
    vera = make_user("vera", "viewer")
    job = submit(local_client, dict(TINY, spp=1024, width=64, height=64))  # the admin's
    assert vera.get(f"/jobs/{job['id']}").status_code == 200
    assert job["id"] in {j["id"] for j in vera.get("/jobs").json()}
    for method, path in (("POST", f"/jobs/{job['id']}/cancel"), ("DELETE", f"/jobs/{job['id']}"),
                         ("POST", f"/jobs/{job['id']}/pause")):
        response = vera.request(method, path)
        assert response.status_code == 403, (method, path)
        assert "viewer" in response.json()["detail"]
    response = vera.post("/jobs", json=TINY)
    assert response.status_code == 403 and "viewer" in response.json()["detail"]
    assert vera.get("/users").status_code == 403
    assert local_client.post(f"/jobs/{job['id']}/cancel").status_code == 200


def test05_tokens_are_random_hashed_shown_once_revocable_and_expire(local_app, local_client,
                                                                     local_settings):
    assert local_client.post("/users", json={"name": "erin", "role": "artist"}).status_code == 201
    assert local_client.post("/users", json={"name": "erin"}).status_code == 409
    assert local_client.post("/users", json={"name": "Bad Name!"}).status_code == 422
    created = local_client.post("/tokens", json={"user": "erin", "label": "laptop"}).json()
    secret = created["token"]
    assert secret.startswith("rf_") and len(secret) >= 3 + 43  # 256 bits, base64url
    second = local_client.post("/tokens", json={"user": "erin"}).json()["token"]
    assert second != secret
    listed = local_client.get("/tokens", params={"user": "erin"}).json()
    assert {t["id"] for t in listed} >= {created["id"]}
    assert all("token" not in t for t in listed)  # never shown again
    # The ledger holds only the hash.
    db = sqlite3.connect(local_settings.data_dir / "rayfarm.sqlite3")
    dump = "\n".join(db.iterdump())
    db.close()
    assert secret not in dump and auth.hash_secret(secret) in dump
    erin = TestClient(local_app, headers={"Authorization": f"Bearer {secret}"})
    assert erin.get("/auth/me").json() == {"user": "erin", "role": "artist", "via": "bearer",
                                           "token_id": created["id"]}
    assert local_client.delete(f"/tokens/{created['id']}").status_code == 204
    assert erin.get("/jobs").status_code == 401
    assert local_client.delete("/tokens/nope").status_code == 404
    # Expiry and a disabled user.
    sessions = local_app.state.farm.sessions
    with sessions.begin() as session:
        token, short = auth.create_token(session, "erin", utcnow(),
                                         expires=utcnow() + timedelta(seconds=60))
        token_id = token.id
    assert TestClient(local_app, headers={"Authorization": f"Bearer {short}"}
                      ).get("/jobs").status_code == 200
    with sessions.begin() as session:
        session.get(ApiToken, token_id).expires = utcnow() - timedelta(seconds=1)
    assert TestClient(local_app, headers={"Authorization": f"Bearer {short}"}
                      ).get("/jobs").status_code == 401
    erin2 = TestClient(local_app, headers={"Authorization": f"Bearer {second}"})
    assert erin2.get("/jobs").status_code == 200
    assert local_client.patch("/users/erin", json={"disabled": True}).status_code == 200
    assert erin2.get("/jobs").status_code == 401
    assert local_client.patch("/users/erin", json={"disabled": False}).status_code == 200


def test06_an_upload_is_shared_by_hash_but_seen_and_deleted_per_owner(local_client, make_user):
    from test_service_scenes import room, scene_bytes, upload

    fay, gus, hal = make_user("fay"), make_user("gus"), make_user("hal")
    doc = scene_bytes(room("shared-by-hash"))
    first = upload(fay, doc)
    assert first.status_code == 201, first.text
    scene_id = first.json()["id"]
    assert gus.get(f"/scenes/{scene_id}").status_code == 404
    assert scene_id not in {s["id"] for s in gus.get("/scenes").json()}
    refused = gus.post("/jobs", json=dict(TINY, scene=scene_id))
    assert refused.status_code == 422 and "unknown scene" in refused.text
    assert gus.delete(f"/scenes/{scene_id}").status_code == 404
    # gus uploads the same content: one record, a claim of his own.
    second = upload(gus, doc)
    assert second.status_code == 201 and second.json()["id"] == scene_id
    assert upload(gus, doc).status_code == 200  # his, already
    assert fay.delete(f"/scenes/{scene_id}").status_code == 204
    assert fay.get(f"/scenes/{scene_id}").status_code == 404
    assert gus.get(f"/scenes/{scene_id}").status_code == 200  # his claim stands
    assert hal.get(f"/scenes/{scene_id}").status_code == 404
    assert local_client.get(f"/scenes/{scene_id}").status_code == 200
    assert gus.delete(f"/scenes/{scene_id}").status_code == 204
    assert local_client.get(f"/scenes/{scene_id}").status_code == 404  # the last claim went


def test07_cookie_login_needs_csrf_for_changes_and_refuses_other_origins(local_app, local_client):
    browser = TestClient(local_app, base_url="http://farm.test")
    typed = {"sec-fetch-site": "none"}  # the login URL, typed or clicked in a terminal
    response = browser.get("/", params={"token": TEST_ADMIN_TOKEN}, headers=typed,
                           follow_redirects=False)
    assert response.status_code == 303 and response.headers["location"] == "/"
    cookies = response.headers.get_list("set-cookie")
    session_cookie = next(c for c in cookies if c.startswith("rayfarm_session="))
    assert "HttpOnly" in session_cookie and "SameSite=strict" in session_cookie
    assert TEST_ADMIN_TOKEN not in " ".join(cookies)  # a session of its own, not the token
    csrf = browser.cookies["rayfarm_csrf"]
    assert browser.get("/auth/me").json()["via"] == "cookie"
    job = submit(local_client, dict(TINY, spp=4096, width=64, height=64))
    path = f"/jobs/{job['id']}/cancel"
    # What another site's form or fetch can send: no CSRF header, maybe text/plain, its Origin.
    assert browser.post(path, content="x", headers={"content-type": "text/plain"}
                        ).status_code == 403
    assert browser.post(path, headers={"x-csrf-token": csrf, "origin": "http://evil.test"}
                        ).status_code == 403
    assert browser.post(path, headers={"x-csrf-token": "wrong"}).status_code == 403
    assert local_client.get(f"/jobs/{job['id']}").json()["status"] != "canceled"
    assert browser.post(path, headers={"x-csrf-token": csrf,
                                       "origin": "http://farm.test"}).status_code == 200
    # A bad login link; logout ends the session.
    bad = browser.get("/", params={"token": "rf_nope"}, headers=typed, follow_redirects=False)
    assert bad.status_code == 303 and bad.headers["location"].startswith("/#/login")
    assert browser.post("/auth/logout", headers={"x-csrf-token": csrf}).status_code == 204
    assert browser.get("/auth/me").status_code == 401
    relogin = TestClient(local_app, base_url="http://farm.test")
    assert relogin.post("/auth/login", json={"token": "rf_nope"}).status_code == 401
    assert relogin.post("/auth/login", json={"token": TEST_ADMIN_TOKEN}).status_code == 200
    assert relogin.get("/auth/me").json()["user"] == "admin"


def test08_security_headers_everywhere_and_no_cors_by_default(local_client, local_settings):
    for path in ("/", "/jobs", "/static/js/main.js", "/healthz", "/nope"):
        headers = local_client.get(path).headers
        assert headers["x-content-type-options"] == "nosniff", path
        csp = headers["content-security-policy"]
        assert "frame-ancestors 'none'" in csp and "script-src 'self';" in csp, path
        assert headers["referrer-policy"] == "no-referrer"
    assert "'unsafe-inline'" in local_client.get("/docs").headers["content-security-policy"]
    preflight = local_client.options("/jobs", headers={
        "origin": "http://evil.test", "access-control-request-method": "POST"})
    assert "access-control-allow-origin" not in preflight.headers
    from service.main import create_app

    allowed = local_settings.model_copy(update={"cors_origins": ["http://studio.test"]})
    app = create_app(allowed)  # not started: the middleware answers preflights itself
    answer = TestClient(app).options("/jobs", headers={
        "origin": "http://studio.test", "access-control-request-method": "POST",
        "access-control-request-headers": "authorization"})
    assert answer.headers["access-control-allow-origin"] == "http://studio.test"


def test09_the_first_admin_and_its_token_file(tmp_path):
    from service.db import open_ledger
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "farm", database_url="", admin_token="")
    engine, sessions = open_ledger(settings)
    secret = auth.bootstrap_admin(sessions, settings.data_dir)
    path = auth.admin_token_path(settings.data_dir)
    assert path.read_text().strip() == secret
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert auth.bootstrap_admin(sessions, settings.data_dir) == secret  # a restart: the same
    with sessions() as session:
        assert auth.verify(session, secret, utcnow()) == Principal(
            "admin", "admin", token_id=auth.list_tokens(session, "admin")[0].id)
        auth.revoke_token(session, auth.list_tokens(session, "admin")[0].id, utcnow())
        session.commit()
    assert auth.bootstrap_admin(sessions, settings.data_dir) is None  # revoked: not printed
    engine.dispose()
    with pytest.raises(ValueError):
        auth.bootstrap_admin(sessions, tmp_path / "other", admin_token="short")


def test10_the_admin_cli_manages_users_and_tokens_on_the_ledger(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    env["RAYFARM_DATA_DIR"] = str(tmp_path / "farm")

    def rayfarm(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([*rayfarm_command(), *args], env=env, capture_output=True,
                              text=True, timeout=120)

    assert "added user ivy (artist" in rayfarm("users", "add", "ivy", "--role", "artist").stdout
    assert rayfarm("users", "add", "ivy").returncode == 2
    made = rayfarm("tokens", "create", "ivy", "--label", "render box", "--expires-days", "7")
    assert made.returncode == 0, made.stderr
    secret = made.stdout.strip()
    assert secret.startswith("rf_") and "shown this once" in made.stderr
    token_id = re.search(r"token (\w+) for ivy", made.stderr).group(1)
    listing = rayfarm("tokens", "list").stdout
    assert token_id in listing and "active" in listing and secret not in listing
    assert "ivy" in rayfarm("users", "list").stdout
    assert rayfarm("tokens", "revoke", token_id).returncode == 0
    assert "revoked" in rayfarm("tokens", "list", "--user", "ivy").stdout
    assert rayfarm("users", "set", "ivy", "--role", "viewer").stdout.startswith("ivy: viewer")
    assert rayfarm("users", "add", "boss", "--role", "admin").returncode == 0
    last = rayfarm("users", "set", "boss", "--disable")
    assert last.returncode == 2 and "boss' is the last enabled admin" in last.stderr


def _chatter(hub, owner: str, job_id: str = "0123456789ab") -> threading.Event:
    """A busy stream: an event of one of `owner`'s jobs every 20 ms, until set."""
    stop = threading.Event()

    def publish():
        while not stop.wait(0.02):
            hub.publish("job", job_id, {"id": job_id, "status": "running"}, owner=owner)
    threading.Thread(target=publish, daemon=True).start()
    return stop


class _Reader:
    """Reads a stream (a response, or its iter_lines) in a thread, as a client
    that keeps up with it does; the lines go to `lines`."""

    def __init__(self, lines_of):
        source = lines_of.iter_lines() if hasattr(lines_of, "iter_lines") else lines_of
        self.lines: list[str] = []
        self._thread = threading.Thread(target=lambda: self.lines.extend(source), daemon=True)
        self._thread.start()

    def ended(self, timeout: float = 10.0) -> bool:
        """Did the server end the stream within `timeout` seconds?"""
        self._thread.join(timeout)  # iter_lines returns once the server ends the stream
        return not self._thread.is_alive()


def _ends(lines_of, timeout: float = 10.0) -> bool:
    return _Reader(lines_of).ended(timeout)


def test11_a_revoked_token_ends_its_busy_event_streams_at_once(local_client, make_user,
                                                               monkeypatch):
    from service.api.routes import events

    # No keep-alive comes in the test's time: the revocation alone must end the stream.
    monkeypatch.setattr(events, "KEEPALIVE", 3600.0)
    kim = make_user("kim")
    token_id = kim.get("/auth/me").json()["token_id"]
    stop = _chatter(local_client.app.state.farm.events, "kim")
    try:
        with kim.stream("GET", "/events") as response:
            assert response.status_code == 200
            reader = _Reader(response)
            wait_for(lambda: any(line.startswith("event: job") for line in reader.lines), 30,
                     "the stream to carry kim's events")
            assert local_client.delete(f"/tokens/{token_id}").status_code == 204
            assert reader.ended(), "the stream of a revoked token goes on"
    finally:
        stop.set()


def test12_logging_out_ends_the_dashboards_event_streams(local_app, monkeypatch):
    from service.api.routes import events

    monkeypatch.setattr(events, "KEEPALIVE", 3600.0)
    browser = TestClient(local_app, base_url="http://farm.test")
    assert browser.post("/auth/login", json={"token": TEST_ADMIN_TOKEN}).status_code == 200
    with browser.stream("GET", "/events") as response:
        assert response.status_code == 200
        assert browser.post("/auth/logout",
                            headers={"x-csrf-token": browser.cookies["rayfarm_csrf"]}
                            ).status_code == 204
        assert _ends(response), "the stream of a logged-out session goes on"
    # The API token it logged in with still works elsewhere.
    assert TestClient(local_app, headers=ADMIN_HEADERS).get("/auth/me").status_code == 200


def test13_the_last_enabled_admin_can_be_neither_disabled_nor_demoted(local_client, tmp_path):
    """Before, an admin could disable the last admin (itself included): nobody
    could manage users any more. A 409 names the reason."""
    for change in ({"disabled": True}, {"role": "artist"}, {"role": "viewer"}):
        refused = local_client.patch("/users/admin", json=change)
        assert refused.status_code == 409, (change, refused.text)
        assert "last enabled admin" in refused.json()["detail"]
    assert local_client.patch("/users/admin", json={"share": 1.0}).status_code == 200
    assert local_client.get("/auth/me").json()["role"] == "admin"
    # With a second admin one of them may go; then the other is the last.
    assert local_client.post("/users", json={"name": "ada-admin", "role": "admin"}
                             ).status_code == 201
    assert local_client.patch("/users/ada-admin", json={"disabled": True}).status_code == 200
    assert local_client.patch("/users/admin", json={"disabled": True}).status_code == 409
    # The same rule in the domain: two admins demoting each other, one after the other.
    from service.db import open_ledger
    from service.errors import Conflict
    from service.settings import Settings

    engine, sessions = open_ledger(Settings(data_dir=tmp_path / "farm", database_url=""))
    try:
        with sessions.begin() as session:
            auth.add_user(session, "a", "admin", utcnow())
            auth.add_user(session, "b", "admin", utcnow())
        with sessions.begin() as session:
            auth.set_user(session, "a", role="artist")
        with pytest.raises(Conflict), sessions.begin() as session:
            auth.set_user(session, "b", role="artist")
        with sessions() as session:
            assert session.get(User, "b").role == "admin"
    finally:
        engine.dispose()


def test14_a_user_disabled_on_the_ledger_loses_its_streams_and_no_one_else(local_app,
                                                                          make_user,
                                                                          monkeypatch):
    """Disabled, or given another role, on the ledger itself (as `rayfarm users set`
    or another replica would): the streams of that user end, busy or idle."""
    from service.api.routes import events

    monkeypatch.setattr(events, "KEEPALIVE", 3600.0)
    farm = local_app.state.farm
    lea, max_ = make_user("lea"), make_user("max")
    stop = _chatter(farm.events, "lea")
    try:
        with lea.stream("GET", "/events") as busy, max_.stream("GET", "/events") as idle:
            assert busy.status_code == idle.status_code == 200
            reader, other = _Reader(busy), _Reader(idle)
            wait_for(lambda: any(line.startswith("event: job") for line in reader.lines), 30,
                     "the stream to carry lea's events")
            with farm.sessions.begin() as session:
                auth.set_user(session, "lea", disabled=True)
            assert reader.ended(), "the stream of a disabled user goes on"
            # Max's stream is still there: it carries his next event.
            farm.events.publish("job", "fedcba987654", {"id": "fedcba987654"}, owner="max")
            wait_for(lambda: any("fedcba987654" in line for line in other.lines), 10,
                     "max's stream to carry his event")
            assert not other.ended(0)
            with farm.sessions.begin() as session:
                auth.set_user(session, "max", role="viewer")
            assert other.ended(), "the stream of a user with another role goes on"
    finally:
        stop.set()
    assert lea.get("/auth/me").status_code == 401 and max_.get("/auth/me").json()["role"] == "viewer"


def test15_a_login_link_from_another_site_logs_nobody_in(local_app):
    """`/?token=` is traded for a session at once only for a navigation the user
    made (Sec-Fetch-Site none: typed, or clicked in a terminal) or from the
    dashboard itself; from another site (another port of this host is the same
    *site*), or a browser that does not say, the dashboard is served and asks."""
    for where in ("cross-site", "same-site", None):
        browser = TestClient(local_app, base_url="http://farm.test")
        headers = {"sec-fetch-site": where} if where else {}
        page = browser.get("/", params={"token": TEST_ADMIN_TOKEN}, headers=headers,
                           follow_redirects=False)
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "set-cookie" not in page.headers and not browser.cookies, where
        assert browser.get("/auth/me").status_code == 401
    for where in ("none", "same-origin"):
        browser = TestClient(local_app, base_url="http://farm.test")
        login = browser.get("/", params={"token": TEST_ADMIN_TOKEN},
                            headers={"sec-fetch-site": where}, follow_redirects=False)
        assert login.status_code == 303 and login.headers["location"] == "/", where
        assert browser.get("/auth/me").json()["via"] == "cookie"


def test16_the_service_answers_only_to_its_names_and_redirects_by_path(local_app, local_client):
    stranger = TestClient(local_app, base_url="http://rebound.example", headers=ADMIN_HEADERS)
    for path in ("/jobs", "/healthz", "/"):
        refused = stranger.get(path)
        assert refused.status_code == 400, (path, refused.text)
        assert "RAYFARM_ALLOWED_HOSTS" in refused.json()["detail"]
    for host in ("localhost:8000", "127.0.0.1", "[::1]:8000", "LOCALHOST.", "testserver:80"):
        assert local_client.get("/auth/me", headers={"host": host}).status_code == 200, host
    # The trailing-slash redirect names no host: the one the request gave is the caller's word.
    moved = local_client.get("/jobs/", params={"limit": 1}, follow_redirects=False)
    assert moved.status_code == 307 and moved.headers["location"] == "/jobs?limit=1"
    # The default: what `rayfarm serve --host` listens on, and always the loopback names.
    from service.api.security import allowed_hosts
    from service.settings import Settings

    assert allowed_hosts([], bind="10.1.2.3") == ["10.1.2.3", "127.0.0.1", "::1", "localhost"]
    assert socket.gethostname().lower() in allowed_hosts([], bind="0.0.0.0")
    assert allowed_hosts(["Farm.Example.com", "*.studio.test"], bind="0.0.0.0") == [
        "*.studio.test", "127.0.0.1", "::1", "farm.example.com", "localhost"]
    assert Settings(allowed_hosts="a.test, b.test").allowed_hosts == ["a.test", "b.test"]
