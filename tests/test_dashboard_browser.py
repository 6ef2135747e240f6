"""The dashboard in a real headless Chromium (Debian's, at /usr/bin/chromium,
driven by Playwright) against a real `rayfarm serve` in embedded mode.

Every test saves screenshots to test-artifacts/screenshots/ and fails if the
page throws, logs an error (but those it announces with
`page.allow_console_error`, such as the 401s of a test that logs out), or
requests anything from another host (the dashboard must work offline).

`page` is logged in as the admin through the login URL; `anon_page` is not
logged in at all (test09 onwards: logging in and out, CSRF, CSP, roles).
"""

from __future__ import annotations

import os
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx
import pytest

from conftest import (ADMIN_HEADERS, ROOT, TEST_ADMIN_TOKEN, TINY, assert_bit_identical,
                      channels_of, poll_job, real_scenes, wait_for, zip_of_folder)

CHROMIUM = os.environ.get("RAYFARM_CHROMIUM", "/usr/bin/chromium")
SHOTS = ROOT / "test-artifacts" / "screenshots"
# As root in a container: no sandbox; no background traffic to Google's hosts.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-dev-shm-usage"]
SLOW = {"scene": "cornell-box", "method": "path", "spp": 4096, "depth": 5, "width": 256,
        "height": 256, "tile_size": 32, "seed": 3}  # minutes of work: still running when canceled


@pytest.fixture(scope="module")
def server(embedded_serve):
    """The base URL of a `rayfarm serve` in embedded mode (conftest's `embedded_serve`)."""
    return embedded_serve[1]


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        message = f"no Chromium at {CHROMIUM} (apt-get install chromium; .ci/run does)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture
def anon_page(browser, server):
    """A fresh page (1440 x 900, a laptop screen) in a browser context of its
    own, not logged in, whose problems fail the test. A test that provokes an
    error on purpose (a 401 after logging out) says so first:
    `page.allow_console_error("status of 401")`."""
    context = browser.new_context(viewport={"width": 1440, "height": 900})
    page = context.new_page()
    problems: list[str] = []
    allowed = ["422"]  # the submit form's validation answers (test03)
    page.allow_console_error = allowed.append
    page.on("pageerror", lambda exc: problems.append(f"page error: {exc}"))
    page.on("console", lambda msg: problems.append(f"console {msg.type}: {msg.text}")
            if msg.type == "error" and not any(a in msg.text for a in allowed) else None)
    page.on("request", lambda req: problems.append(f"request to another host: {req.url}")
            if not req.url.startswith((server, "data:", "blob:")) else None)
    page.set_default_timeout(60_000)
    # A console error names no URL ("Failed to load resource: ... 404"): the
    # failed responses go to stdout, which pytest shows with a failure.
    page.on("response", lambda r: print(f"HTTP {r.status} {r.url}") if r.status >= 400 else None)
    page.base = server
    yield page
    context.close()
    assert not problems, problems


@pytest.fixture
def page(anon_page, server):
    """`anon_page`, logged in as the admin."""
    anon_page.goto(f"{server}/?token={TEST_ADMIN_TOKEN}")  # the login URL `rayfarm serve` prints
    anon_page.wait_for_url(f"{server}/")
    return anon_page


@pytest.fixture(scope="module")
def login_url(embedded_serve):
    """The login URL the module's `rayfarm serve` printed when it started."""
    match = re.search(r"http://\S+/\?token=\S+", embedded_serve[0].log())
    assert match, embedded_serve[0].log()
    return match.group(0)


@pytest.fixture
def other_origin():
    """A page of another origin: http://127.0.0.1:<another port>/ (same site as the
    service, as SameSite counts sites: its requests do carry the cookies)."""
    class Page(BaseHTTPRequestHandler):
        def do_GET(self):
            body = b"<!doctype html><title>another site</title><p>Nothing to see here.</p>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_port}"
    httpd.shutdown()
    httpd.server_close()


def shot(page, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def api(server: str):
    return httpx.Client(base_url=server, timeout=30, headers=ADMIN_HEADERS)


def progress_value(page) -> int:
    return int(page.get_attribute("#view .progress.big", "aria-valuenow"))


def test01_submit_through_the_form_then_watch_progress_and_preview_change(page):
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-method option[value='path-mis']", state="attached")
    page.wait_for_selector("#f-scene option[value='cornell-box']", state="attached")
    page.select_option("#f-scene", "cornell-box")
    page.select_option("#f-method", "path-mis")
    page.wait_for_selector("#f-opt-heuristic")  # the method's options come from GET /methods
    page.wait_for_selector("#f-sampler option[value='sobol']", state="attached")
    assert page.input_value("#f-sampler") == "sobol"  # the API's default is preselected
    page.select_option("#f-sampler", "sobol")
    for name, value in (("spp", "256"), ("depth", "5"), ("width", "128"), ("height", "128"),
                        ("tile_size", "32"), ("seed", "5")):
        page.fill(f"#f-{name}", value)
    shot(page, "01-submit-form")
    page.click("#submit-button")
    page.wait_for_url("**/#/jobs/*")
    job_id = page.url.rsplit("/", 1)[1]
    with api(page.base) as client:
        job = client.get(f"/jobs/{job_id}").json()
    assert (job["spp"], job["width"], job["sampler"], job["method"]) == (256, 128, "sobol", "path-mis")

    # The preview appears and changes as passes land; the progress bar advances.
    page.wait_for_selector("#stage img#preview[data-loaded]")
    first = page.locator("#stage").screenshot()
    first_src = page.get_attribute("#stage img#preview", "src")
    first_progress = progress_value(page)
    assert first_progress < 100  # read while the job runs: the first pass's preview is up
    values = {first_progress}
    shot(page, "02-job-running")
    page.wait_for_function(
        "src => { const img = document.querySelector('#stage img#preview');"
        " return img && img.dataset.loaded && img.getAttribute('src') !== src; }", arg=first_src)
    assert page.locator("#tile-map .tile").count() == 16  # 4 x 4 tiles of 32 px
    # the bar moves on from the value it had while running (to another
    # intermediate value or to 100: a fast machine may finish the job before
    # a second intermediate value can be read)
    wait_for(lambda: values.add(progress_value(page)) or max(values) > first_progress, 120,
             "the progress bar to advance")
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=240_000)
    assert progress_value(page) == 100
    page.wait_for_function("() => document.querySelector('#stage img#preview')"
                           "?.getAttribute('src').includes('final')")
    page.wait_for_function("() => document.querySelector('#stage img#preview')?.complete")
    last = page.locator("#stage").screenshot()
    assert first != last, "the preview did not change"
    assert page.get_attribute("#download-exr", "href") == f"/jobs/{job_id}/result.exr"
    shot(page, "03-job-done")
    page.click("[data-view='noise']")
    page.wait_for_selector("#stage img#preview[data-view='noise'][data-loaded]")
    shot(page, "04-job-noise-map")
    page.click("[data-view='image']")
    page.check("#show-tiles")
    page.select_option("#color-tiles", "worker")
    assert page.locator("#legend").inner_text().strip().startswith("local@")
    shot(page, "05-job-tiles-by-worker")


def test02_cancel_a_job_from_its_page(page):
    with api(page.base) as client:
        job = client.post("/jobs", json=SLOW).json()
    page.goto(f"{page.base}/#/jobs/{job['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='running']", timeout=120_000)
    page.click("button[data-action='cancel']")
    page.wait_for_selector("#view .page-head .badge[data-state='canceled']")
    assert page.is_disabled("button[data-action='cancel']")
    assert page.is_enabled("button[data-action='requeue']")
    shot(page, "06-job-canceled")
    with api(page.base) as client:
        assert client.get(f"/jobs/{job['id']}").json()["status"] == "canceled"
    # ... and delete it (after a confirmation).
    page.once("dialog", lambda dialog: dialog.accept())
    page.click("button[data-action='delete']")
    page.wait_for_url("**/#/jobs")
    with api(page.base) as client:
        assert client.get(f"/jobs/{job['id']}").status_code == 404


def test03_a_bad_spp_shows_the_api_message_next_to_the_field(page):
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-method option", state="attached")
    with api(page.base) as client:
        before = len(client.get("/jobs").json())
    page.fill("#f-spp", "0")
    page.click("#submit-button")
    message = page.wait_for_selector("[data-error-for='spp']:not(:empty)")
    assert "must be between 1 and" in message.inner_text()
    assert "invalid" in page.get_attribute("[data-field='spp']", "class")
    assert page.url.endswith("#/submit")  # no job was made
    shot(page, "07-submit-validation")
    with api(page.base) as client:
        assert len(client.get("/jobs").json()) == before


def test04_the_jobs_list_updates_live_and_filters(page):
    page.goto(f"{page.base}/#/jobs")
    page.wait_for_selector("#jobs-table")
    with api(page.base) as client:
        job = client.post("/jobs", json=dict(SLOW, spp=64, width=64, height=64, tile_size=32)).json()
    page.wait_for_selector(f"tr[data-job='{job['id']}']")  # no reload
    page.wait_for_selector(f"tr[data-job='{job['id']}'] .badge[data-state='done']",
                           timeout=120_000)
    assert "100%" in page.inner_text(f"tr[data-job='{job['id']}']")
    page.click("button[data-status='canceled']")
    page.wait_for_selector(f"tr[data-job='{job['id']}']", state="detached")
    page.click("button[data-status='done']")
    page.wait_for_selector(f"tr[data-job='{job['id']}']")
    page.click("button[data-status='all']")
    shot(page, "08-jobs-list")


def test05_the_workers_page_shows_the_pool(page):
    page.goto(f"{page.base}/#/workers")
    row = page.wait_for_selector("#workers-table tr[data-worker^='local@']")
    assert row.get_attribute("data-state") in ("idle", "busy")
    assert "local pool" in row.inner_text()
    # The top bar says this replica runs the scheduler (service.leader).
    page.locator("#health", has_text="scheduler here (").wait_for()
    shot(page, "09-workers")


def test06_the_api_docs_load_offline(page):
    page.goto(f"{page.base}/docs")
    page.wait_for_selector(".swagger-ui .info .title")
    assert "rayfarm" in page.inner_text(".swagger-ui .info .title")
    shot(page, "10-api-docs")


def test07_upload_a_scene_with_its_mesh_through_the_form_and_render_it(page, tmp_path):
    from test_service_scenes import CUBE_OBJ, room

    scene = tmp_path / "browser-room.json"
    scene.write_text(__import__("json").dumps(room("browser-room")))
    (tmp_path / "cube.obj").write_text(CUBE_OBJ)
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-scene option", state="attached")
    # A scene file without the mesh it references: the API's message, next to the upload.
    page.set_input_files("#f-upload", [str(scene)])
    page.click("#upload-button")
    error = page.wait_for_selector("[data-error-for='upload']:not(:empty)")
    assert "shapes[6].file" in error.inner_text() and "cube.obj" in error.inner_text()
    page.set_input_files("#f-upload", [str(scene), str(tmp_path / "cube.obj")])
    page.click("#upload-button")
    page.wait_for_function("() => document.querySelector('#f-scene').selectedOptions[0]"
                           "?.textContent.includes('browser-room')")
    # Its thumbnail is rendered in the background; the form shows it once it is there.
    page.wait_for_function("() => { const i = document.querySelector('#scene-thumb img');"
                           " return i && i.complete && i.naturalWidth > 0; }")
    for name, value in (("spp", "4"), ("width", "64"), ("height", "48"), ("tile_size", "32")):
        page.fill(f"#f-{name}", value)
    shot(page, "11-submit-uploaded-scene")
    page.click("#submit-button")
    page.wait_for_url("**/#/jobs/*")
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=120_000)
    assert "browser-room" in page.inner_text("#view .page-head")
    # A folder (the folder picker: each file with its path), the mesh in a
    # subfolder, two scene files at the top: the form asks which, then uploads.
    folder = tmp_path / "browser-folder"
    (folder / "models").mkdir(parents=True)
    doc = room("browser-folder")
    doc["shapes"][-1]["file"] = "models/cube.obj"
    for name in ("room.json", "copy.json"):
        (folder / name).write_text(__import__("json").dumps(doc))
    (folder / "models" / "cube.obj").write_text(CUBE_OBJ)
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-scene option", state="attached")
    page.set_input_files("#f-upload-folder", str(folder))
    page.click("#upload-button")
    error = page.wait_for_selector("[data-error-for='main']:not(:empty)")
    assert "copy.json" in error.inner_text() and "room.json" in error.inner_text()
    page.fill("#f-main", "room.json")
    page.click("#upload-button")
    page.wait_for_function("() => document.querySelector('#f-scene').selectedOptions[0]"
                           "?.textContent.includes('browser-folder')")
    info = page.inner_text("#scene-info") + page.inner_text("#scene-report")
    assert "browser-folder/room.json" in info and "Imported as written" in info, info
    assert page.is_hidden("[data-field='main']")
    shot(page, "11b-submit-uploaded-folder")


def test07b_a_zipped_mitsuba_folder_uploads_renders_and_downloads_the_renderers_own_exr(
        page, tmp_path, reference_channels):
    """veach-bidir's folder zipped as a user zips it, chosen in the upload's
    file picker, rendered small through the form with its depth untouched
    (blank: the file's); the EXR downloaded from the job page is bit for bit
    the renderer's own render of scene.xml with the job's spec."""
    from renderer import scene_text
    from renderer.cli import load_scene as read_scene_file  # what `rayfarm render FILE` reads

    from test_service_scenes import VEACH_DEPTH, VEACH_JOB

    folder = real_scenes("veach-bidir/scene.xml") / "veach-bidir"
    archive = zip_of_folder(folder, tmp_path)
    local = read_scene_file(str(folder / "scene.xml"))
    scene_id = scene_text(local)[0]
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-method option[value='path-mis']", state="attached")
    page.set_input_files("#f-upload", str(archive))
    page.click("#upload-button")
    page.wait_for_function("id => document.querySelector('#f-scene').value === id", arg=scene_id)
    page.select_option("#f-method", "path-mis")
    for name in ("spp", "width", "height", "tile_size", "seed"):
        page.fill(f"#f-{name}", str(VEACH_JOB[name]))
    page.click("#submit-button")
    page.wait_for_url("**/#/jobs/*")
    job_id = page.url.rsplit("/", 1)[1]
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=120_000)
    shot(page, "11c-veach-bidir-rendered")
    with page.expect_download() as download:
        page.click("#download-exr")
    download.value.save_as(tmp_path / "farm.exr")
    with api(page.base) as client:
        job = client.get(f"/jobs/{job_id}").json()
    assert {k: job[k] for k in VEACH_JOB} == VEACH_JOB and job["scene_hash"] == scene_id
    assert job["depth"] == VEACH_DEPTH
    assert_bit_identical(channels_of(tmp_path / "farm.exr"), reference_channels(
        dict(VEACH_JOB, scene=local, depth=VEACH_DEPTH, sampler=job["sampler"])))


def test07c_the_forms_depth_is_blank_showing_the_scenes_own(page):
    """The form's depth starts blank, its placeholder the chosen scene's
    default depth (an uploaded Mitsuba file's, a built-in's 5): a job sent
    with it untouched renders at the file's depth, not the form's."""
    from test_service_scenes import ATTIC, ATTIC_DEPTH

    with api(page.base) as client:
        response = client.post("/scenes", files=[("files", (f"attic/{name}", data))
                                                 for name, data in ATTIC.items()])
        assert response.status_code in (200, 201), response.text
    scene_id = response.json()["id"]
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector(f"#f-scene option[value='{scene_id}']", state="attached")
    page.select_option("#f-scene", "cornell-box")
    assert page.input_value("#f-depth") == ""
    assert page.get_attribute("#f-depth", "placeholder") == "5"
    page.select_option("#f-scene", scene_id)
    assert page.input_value("#f-depth") == ""
    assert page.get_attribute("#f-depth", "placeholder") == str(ATTIC_DEPTH)
    for name, value in (("spp", "1"), ("width", "16"), ("height", "12")):
        page.fill(f"#f-{name}", value)
    page.click("#submit-button")
    page.wait_for_url("**/#/jobs/*")
    with api(page.base) as client:
        job = client.get(f"/jobs/{page.url.rsplit('/', 1)[1]}").json()
    assert (job["scene_hash"], job["depth"]) == (scene_id, ATTIC_DEPTH)


def test08_a_dag_job_shows_its_phases(page):
    """A photon-mapping job plans photon passes then gather tiles: the job page
    lists both phases with their units done, and each unit's phase."""
    body = {"scene": "cornell-caustic", "method": "photon", "spp": 4, "depth": 5, "width": 96,
            "height": 96, "tile_size": 48, "seed": 2, "progressive": False,
            "options": {"iterations_per_unit": 1}}
    with api(page.base) as client:
        job = client.post("/jobs", json=body).json()
    page.goto(f"{page.base}/#/jobs/{job['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=180_000)
    page.wait_for_selector("#phases .phase[data-phase='gather']")
    phases = page.eval_on_selector_all("#phases .phase", "els => els.map(e => [e.dataset.phase, "
                                       "e.querySelector('.label').textContent])")
    with api(page.base) as client:
        units = client.get(f"/jobs/{job['id']}/units").json()
    counts = {kind: sum(u["kind"] == kind for u in units) for kind in ("photons", "gather")}
    assert [p[0] for p in phases] == ["photons", "gather"]
    for kind, label in phases:
        assert label.startswith(f"{counts[kind]} / {counts[kind]}"), (kind, label)
    cells = page.eval_on_selector_all("#units-table tbody tr td:nth-child(2)",
                                      "els => els.map(e => e.textContent)")
    assert any(c.startswith("photons (stage") for c in cells) and \
        any(c.startswith("gather (stage") for c in cells)
    page.wait_for_selector("#stage img#preview[data-loaded]")
    shot(page, "12-dag-job-phases")


# -- logging in and out, CSRF, CSP, roles ------------------------------------------------

def cookies_of(page) -> dict[str, dict]:
    """The browser's cookies for the service, HttpOnly ones included."""
    return {c["name"]: c for c in page.context.cookies(page.base)}


def log_in_on_the_form(page, token: str) -> None:
    page.wait_for_selector("#login-form")
    page.fill("#login-token", token)
    page.click("#login-button")


def wait_done(base: str, job_id: str, headers: dict = ADMIN_HEADERS) -> dict:
    with httpx.Client(base_url=base, timeout=30, headers=headers) as client:
        return poll_job(lambda path: client.get(path).json(), job_id)


def test09_the_printed_login_url_logs_in_and_leaves_the_address_bar(anon_page, login_url):
    page = anon_page
    assert TEST_ADMIN_TOKEN in login_url  # the URL `rayfarm serve` printed, from its log
    page.goto(login_url)
    page.wait_for_url(f"{page.base}/")  # 303 to `/`: the token left the address bar
    assert "token" not in page.url and TEST_ADMIN_TOKEN not in page.url
    page.wait_for_selector("#jobs-table")
    assert page.inner_text("#whoami-user") == "admin"
    assert page.text_content("#whoami-role") == "admin"
    assert page.is_visible("#logout")
    # The session cookie is HttpOnly (no script reads it); the CSRF cookie is
    # meant for the dashboard's script. Both SameSite=Strict.
    script_sees = page.evaluate("document.cookie")
    assert "rayfarm_session" not in script_sees and "rayfarm_csrf=" in script_sees
    jar = cookies_of(page)
    assert jar["rayfarm_session"]["httpOnly"] and jar["rayfarm_session"]["sameSite"] == "Strict"
    assert not jar["rayfarm_csrf"]["httpOnly"] and jar["rayfarm_csrf"]["sameSite"] == "Strict"
    assert TEST_ADMIN_TOKEN not in {c["value"] for c in jar.values()}  # a session, not the token
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.locator(".topbar").screenshot(path=str(SHOTS / "13-topbar-admin.png"))
    shot(page, "14-logged-in-by-url")


def test10_logout_then_log_in_again_by_pasting_the_token(page):
    page.goto(f"{page.base}/#/workers")
    page.wait_for_selector("#workers-table tr[data-worker]")
    old_session = cookies_of(page)["rayfarm_session"]["value"]
    page.allow_console_error("status of 401")  # from here on, 401s are what we look for
    page.click("#logout")
    page.wait_for_url("**/#/login")
    page.wait_for_selector("#login-form")
    assert not page.is_visible("#whoami-user") and not page.is_visible("#logout")
    assert "rayfarm_session" not in cookies_of(page)
    statuses = page.evaluate("async () => Promise.all(['/jobs', '/workers', '/auth/me', '/scenes']"
                             ".map(async (path) => (await fetch(path)).status))")
    assert statuses == [401, 401, 401, 401]
    # The login was revoked, not only forgotten by this browser.
    answer = httpx.get(f"{page.base}/auth/me", headers={"Cookie": f"rayfarm_session={old_session}"})
    assert answer.status_code == 401, answer.text
    shot(page, "15-logged-out")

    # Going somewhere without a login: the login page, which goes on there afterwards.
    page.goto(f"{page.base}/#/workers")
    page.wait_for_url(re.compile(r".*#/login\?next=%23%2Fworkers$"))
    log_in_on_the_form(page, "rf_not-a-token")
    assert "not accepted" in page.inner_text("#login-refused")
    assert "#/login" in page.url and "rayfarm_session" not in cookies_of(page)
    shot(page, "16-login-refused")
    log_in_on_the_form(page, f"  {TEST_ADMIN_TOKEN}\n")  # pasted with blanks around it
    page.wait_for_url("**/#/workers")
    page.wait_for_selector("#workers-table tr[data-worker]")
    assert page.inner_text("#whoami-user") == "admin"
    assert page.evaluate("fetch('/auth/me').then((r) => r.json())")["via"] == "cookie"


def test11_a_bad_login_link_lands_on_the_login_page_saying_so(anon_page):
    page = anon_page
    page.goto(f"{page.base}/")  # no login: the login page, which says where tokens come from
    page.wait_for_url(re.compile(r".*#/login\?next=%23%2Fjobs$"))
    help_text = page.inner_text("#login-help")
    assert "rayfarm serve" in help_text and "rayfarm tokens create USER" in help_text
    assert not page.is_visible("#login-failed")
    shot(page, "17-login")
    page.goto(f"{page.base}/?token=rf_not-a-token")
    page.wait_for_url("**/#/login?failed=1")
    assert "token was not accepted" in page.inner_text("#login-failed")
    assert not page.is_visible("#whoami-user")
    assert "rayfarm_session" not in cookies_of(page)
    shot(page, "18-login-link-refused")


def test12_csrf_another_origin_cannot_cancel_nor_a_request_without_the_header(page, other_origin,
                                                                              embedded_serve):
    def answered(method: str, path: str) -> int:
        """The status the service answered, from its access log (the browser
        does not let the other page read it: Cross-Origin-Resource-Policy)."""
        line = re.compile(rf'"{method} {re.escape(path)} HTTP/1.1" (\d{{3}})')
        return int(wait_for(lambda: line.search(embedded_serve[0].log()), 10,
                            f"{method} {path} in the service's log").group(1))

    with api(page.base) as client:
        job = client.post("/jobs", json=SLOW).json()
    try:
        page.goto(f"{page.base}/#/jobs/{job['id']}")
        page.wait_for_selector("#view .page-head .badge")
        # A page of another origin, while this browser is logged in. 127.0.0.1 on
        # another port is the same *site*: SameSite=Strict lets the cookies through
        # (the probe is answered 200, as the logged-in admin), so the service's
        # own check must refuse the cancel.
        other = page.context.new_page()
        other.goto(f"{other_origin}/")
        fetch = """url => fetch(url, {method: 'POST', mode: 'no-cors', credentials: 'include',
            headers: {'Content-Type': 'text/plain'}, body: 'x'}).then(() => 'read', (err) => 'unread')"""
        probe = f"/auth/me?probe={job['id']}"
        other.evaluate("url => fetch(url, {mode: 'no-cors', credentials: 'include'})"
                       ".then(() => 'read', (err) => 'unread')", f"{page.base}{probe}")
        assert answered("GET", probe) == 200
        other.evaluate(fetch, f"{page.base}/jobs/{job['id']}/cancel")
        assert answered("POST", f"/jobs/{job['id']}/cancel") == 403
        other.close()
        with api(page.base) as client:
            assert client.get(f"/jobs/{job['id']}").json()["status"] in ("queued", "running")
        # The dashboard's own origin, without the X-CSRF-Token header: refused too.
        page.allow_console_error("status of 403")
        status = page.evaluate("id => fetch(`/jobs/${id}/cancel`, {method: 'POST'}).then((r) => r.status)",
                               job["id"])
        assert status == 403
        with api(page.base) as client:
            assert client.get(f"/jobs/{job['id']}").json()["status"] in ("queued", "running")
        # ... and with it, as the dashboard sends it, the cookie login may cancel.
        status = page.evaluate("""id => fetch(`/jobs/${id}/cancel`, {method: 'POST', headers: {
            'X-CSRF-Token': decodeURIComponent(/rayfarm_csrf=([^;]*)/.exec(document.cookie)[1])}})
            .then((r) => r.status)""", job["id"])
        assert status == 200
        with api(page.base) as client:
            assert client.get(f"/jobs/{job['id']}").json()["status"] == "canceled"
    finally:
        with api(page.base) as client:
            client.post(f"/jobs/{job['id']}/cancel")


CSP_WATCH = """document.addEventListener('securitypolicyviolation',
  (e) => (window.__cspViolations ||= []).push(`${e.violatedDirective} ${e.blockedURI}`));"""


def test13_no_csp_violation_on_any_dashboard_page_and_the_docs_still_render(page):
    with api(page.base) as client:
        job = client.post("/jobs", json=TINY).json()
    wait_done(page.base, job["id"])
    reports: list[str] = []
    page.on("console", lambda msg: reports.append(msg.text)
            if "Content Security Policy" in msg.text else None)
    page.add_init_script(CSP_WATCH)
    page.goto(f"{page.base}/#/jobs")
    response = page.reload()  # a fresh load: the watcher is in
    policy = response.headers["content-security-policy"]
    assert "script-src 'self';" in policy and "style-src 'self';" in policy
    assert "unsafe-inline" not in policy
    page.wait_for_selector(f"tr[data-job='{job['id']}'] .badge[data-state='done']")
    page.goto(f"{page.base}/#/jobs/{job['id']}")
    page.wait_for_selector("#stage img#preview[data-loaded]")
    page.check("#show-tiles")
    page.select_option("#color-tiles", "worker")
    page.wait_for_selector("#legend .sw")
    page.click("[data-view='noise']")
    page.wait_for_selector("#stage img#preview[data-view='noise'][data-loaded]")
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-opt-heuristic")
    page.wait_for_selector("#scene-thumb img")
    page.goto(f"{page.base}/#/workers")
    page.wait_for_selector("#workers-table tr[data-worker]")
    page.goto(f"{page.base}/#/login")
    page.wait_for_selector("#login-already")
    page.wait_for_timeout(300)  # reports are asynchronous
    assert reports == []
    assert page.evaluate("window.__cspViolations || []") == []
    # The watch itself works: an inline style it is shown is reported.
    page.allow_console_error("Content Security Policy")
    page.evaluate("document.body.setAttribute('style', 'outline: 1px solid red')")
    wait_for(lambda: reports and page.evaluate("window.__cspViolations || []"), 10,
             "the planted violation to be reported")

    # Swagger UI, under its own policy, with the schema it loads by the cookie login.
    page.goto(f"{page.base}/docs")
    page.wait_for_selector(".swagger-ui .opblock")
    assert "rayfarm" in page.inner_text(".swagger-ui .info .title")
    assert page.locator(".swagger-ui .opblock").count() > 10


def test14_a_stream_refused_for_want_of_a_login_brings_the_login_page(page):
    page.goto(f"{page.base}/#/login")  # logged in; no view that calls the API
    page.wait_for_selector("#login-already")
    jar = cookies_of(page)
    # The login ends elsewhere (another tab logs out): this browser still holds the cookie.
    answer = httpx.post(f"{page.base}/auth/logout", headers={
        "Cookie": f"rayfarm_session={jar['rayfarm_session']['value']}; "
                  f"rayfarm_csrf={jar['rayfarm_csrf']['value']}",
        "X-CSRF-Token": jar["rayfarm_csrf"]["value"]})
    assert answer.status_code == 204, answer.text
    # The jobs list answers from here, so only its event stream can find out.
    page.route("**/jobs?limit=*", lambda route: route.fulfill(
        status=200, content_type="application/json", body="[]"))
    page.allow_console_error("401")
    with page.expect_response(lambda r: r.url.endswith("/events")) as events:
        page.goto(f"{page.base}/#/jobs")
    assert events.value.status == 401
    page.wait_for_url(re.compile(r".*#/login\?next=%23%2Fjobs&ended=1$"))
    assert "Your login has ended" in page.inner_text("#login-ended")
    assert not page.is_visible("#whoami-user")


def test15_a_viewer_sees_everything_and_changes_nothing_an_artist_its_own(anon_page):
    page = anon_page
    tokens = {}
    with api(page.base) as client:
        for name, role in (("vera", "viewer"), ("arti", "artist")):
            assert client.post("/users", json={"name": name, "role": role}).status_code == 201
            answer = client.post("/tokens", json={"user": name, "label": "browser test"})
            assert answer.status_code == 201, answer.text
            tokens[name] = answer.json()["token"]
        admin_job = client.post("/jobs", json=TINY).json()
    arti = {"Authorization": f"Bearer {tokens['arti']}"}
    with httpx.Client(base_url=page.base, timeout=30, headers=arti) as client:
        arti_job = client.post("/jobs", json=dict(TINY, seed=8)).json()
    wait_done(page.base, admin_job["id"])
    wait_done(page.base, arti_job["id"], arti)

    page.goto(f"{page.base}/#/login")
    log_in_on_the_form(page, tokens["vera"])
    page.wait_for_url("**/#/jobs")
    assert (page.inner_text("#whoami-user"), page.text_content("#whoami-role")) == ("vera", "viewer")
    for job in (admin_job, arti_job):  # every job, with its owner
        page.wait_for_selector(f"tr[data-job='{job['id']}']")
        assert page.inner_text(f"tr[data-job='{job['id']}'] td.owner") == job["owner"]
    assert page.is_disabled("#new-job")
    assert "viewer" in page.inner_text("#read-only-note")
    page.goto(f"{page.base}/#/jobs/{admin_job['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='done']")
    assert page.inner_text("#job-owner .owner") == "admin"
    assert page.inner_text("#param-owner") == "admin"
    for action in ("pause", "resume", "cancel", "retry", "requeue", "set", "delete"):
        assert page.is_disabled(f"button[data-action='{action}']"), action
    assert page.is_disabled("#priority")
    assert "viewer" in page.inner_text("#read-only-note")
    assert "viewer" in page.get_attribute("button[data-action='delete']", "title")
    shot(page, "19-viewer-job")
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-method option", state="attached")
    assert page.is_disabled("#submit-button") and page.is_disabled("#upload-button")
    assert "viewer" in page.inner_text("#read-only-note")
    shot(page, "20-viewer-submit")

    page.click("#logout")
    log_in_on_the_form(page, tokens["arti"])
    page.wait_for_url("**/#/jobs")
    page.wait_for_selector(f"tr[data-job='{arti_job['id']}']")
    assert page.inner_text("#view h1") == "Your jobs"
    owners = page.eval_on_selector_all("#jobs-table td.owner", "els => els.map((e) => e.textContent)")
    assert set(owners) == {"arti"}
    assert page.is_enabled("#new-job")
    page.goto(f"{page.base}/#/jobs/{arti_job['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='done']")
    assert page.is_enabled("button[data-action='requeue']") and page.is_enabled("button[data-action='delete']")
    assert not page.is_visible("#read-only-note")
    shot(page, "21-artist-job")


def test16_a_units_row_opens_its_log_with_lines_and_tracebacks(page, embedded_serve):
    """Clicking a unit's row shows what its tasks logged: a done unit's line from
    the renderer, a failed unit's three tracebacks (its scene text tampered with,
    as tests/test_service_unitlogs.py does)."""
    from test_service_unitlogs import HASH_ERROR, UNIT_LINE, poisoned_scene

    scenes = embedded_serve[0].log_path.parent / "data" / "store" / "scenes"
    poison = poisoned_scene(lambda key: scenes / f"{key}.json")
    with api(page.base) as client:
        done = client.post("/jobs", json=dict(TINY, seed=1601)).json()
        failed = client.post("/jobs", json=dict(TINY, scene=poison, progressive=False)).json()
    assert wait_done(page.base, done["id"])["status"] == "done"
    assert wait_done(page.base, failed["id"])["status"] == "failed"

    page.goto(f"{page.base}/#/jobs/{done['id']}")
    page.wait_for_selector("#units-table tbody tr[data-unit='0']")
    assert page.is_hidden("#unit-log")
    page.click("#units-table tbody tr[data-unit='0']")
    page.wait_for_selector("#unit-log .unit-attempt[data-task='1'] pre.log-lines")
    assert UNIT_LINE in page.text_content("#unit-log pre.log-lines")
    assert page.query_selector("#unit-log pre.log-traceback") is None
    assert "selected" in page.get_attribute("#units-table tbody tr[data-unit='0']", "class")

    page.goto(f"{page.base}/#/jobs/{failed['id']}")
    row = "#units-table tbody tr:has(.badge[data-state='failed'])"
    page.wait_for_selector(row)
    page.click(row)
    page.wait_for_selector("#unit-log .unit-attempt[data-task='3'] pre.log-traceback")
    tracebacks = page.eval_on_selector_all("#unit-log pre.log-traceback",
                                           "els => els.map(e => e.textContent)")
    assert len(tracebacks) == 3 and all(HASH_ERROR in t for t in tracebacks), tracebacks
    shot(page, "16-unit-log")
    page.click("#unit-log-close")
    assert page.is_hidden("#unit-log")


def test17_an_admin_drains_and_enables_a_worker_from_the_workers_page(page):
    page.goto(f"{page.base}/#/workers")
    row = "#workers-table tr[data-worker^='local@']"
    page.wait_for_selector(f"{row}[data-disabled='no']")
    name = page.get_attribute(row, "data-worker")
    with api(page.base) as client:
        try:
            page.click(f"{row} button[data-action='disable']")
            page.wait_for_selector(f"{row}[data-disabled='yes'] button[data-action='enable']")
            assert "disabled" in page.inner_text(row)
            (worker,) = [w for w in client.get("/workers").json() if w["name"] == name]
            assert worker["disabled"] is True  # the service's, not only the page's
            shot(page, "22-worker-disabled")
            page.click(f"{row} button[data-action='enable']")
            page.wait_for_selector(f"{row}[data-disabled='no'] button[data-action='disable']")
            (worker,) = [w for w in client.get("/workers").json() if w["name"] == name]
            assert worker["disabled"] is False
        finally:  # the module's other tests need the pool
            client.post(f"/workers/{name}/enable")


def test18_a_denoised_job_toggles_between_its_raw_and_denoised_image(page):
    """A job submitted with denoise: once done, its page offers a Denoised view
    labelled as a biased post-process, and a download of it; a job without
    denoise has neither."""
    body = {"scene": "cornell-box", "method": "path", "spp": 8, "depth": 3, "width": 64,
            "height": 64, "tile_size": 32, "seed": 5}
    with api(page.base) as client:
        plain = client.post("/jobs", json=body).json()
        job = client.post("/jobs", json=dict(body, denoise=True)).json()
        # Both done before their pages open: the toggle is the subject here.
        for job_id in (plain["id"], job["id"]):
            assert poll_job(lambda path: client.get(path).json(), job_id)["status"] == "done"
    page.goto(f"{page.base}/#/jobs/{job['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=180_000)
    page.click("[data-view='denoised']")
    page.wait_for_selector("#stage img#preview[data-view='denoised'][data-loaded]")
    assert page.get_attribute("#stage img#preview", "src").startswith(
        f"/jobs/{job['id']}/denoised.png")
    assert "biased post-process" in page.text_content(".denoised-note")
    assert page.get_attribute("#download-denoised", "href") == f"/jobs/{job['id']}/denoised.png"
    shot(page, "18-job-denoised")
    page.click("[data-view='image']")
    page.wait_for_selector("#stage img#preview[data-view='image'][data-loaded]")
    page.goto(f"{page.base}/#/jobs/{plain['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=180_000)
    page.wait_for_selector("[data-view='noise']")
    assert page.query_selector("[data-view='denoised']") is None
    assert page.query_selector("#download-denoised") is None


def test19_a_job_submitted_to_a_noise_target_speaks_in_error(page):
    """The form's noise target (%) sends `target`; the job page's progress label
    and rows speak in error ("error 24.1 % -> 25 %"), say why it stopped and
    how many units were skipped, and the units table filters the skipped ones."""
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-method option[value='path-mis']", state="attached")
    page.wait_for_selector("#f-scene option[value='cornell-box']", state="attached")
    page.select_option("#f-method", "path-mis")
    for name, value in (("spp", "1024"), ("depth", "5"), ("width", "32"), ("height", "32"),
                        ("tile_size", "8"), ("seed", "3"), ("target", "25")):
        page.fill(f"#f-{name}", value)
    page.click("#submit-button")
    page.wait_for_url("**/#/jobs/*")
    job_id = page.url.rsplit("/", 1)[1]
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=180_000)
    with api(page.base) as client:
        job = client.get(f"/jobs/{job_id}").json()
    assert job["target"] == {"rel_error": 0.25, "max_spp": 1024, "max_seconds": None}
    assert job["target_stop"] == "target"
    label = page.text_content("#view .progress.big .label")
    assert label.startswith("error ") and label.endswith("→ 25 %"), label
    assert page.text_content("#target-stop") == "target met"
    assert f"{job['progress']['units_skipped']} skipped" in page.text_content("#units")
    assert page.text_content("#param-target") == "25 %"
    # the convergence plot: a dot per pass with a known error, the target's line
    page.wait_for_selector("#convergence svg.plot")
    known = [p for p in job["passes"] if p["rel_error"]]
    assert page.locator("#convergence svg .dot").count() == len(known) >= 2
    assert page.locator("#convergence svg line.target").count() == 1
    # and the same passes against render seconds
    timed = [p for p in known if p["seconds"] > 0]
    assert page.locator("#convergence-time .series-dot").count() == len(timed) >= 2
    page.click("[data-units='skipped']")
    states = page.eval_on_selector_all("#units-table tbody tr td .badge",
                                       "els => els.map(e => e.dataset.state)")
    assert states and set(states) == {"skipped"}
    shot(page, "19-job-noise-target")


def _luminance(rgb) -> float:
    """WCAG relative luminance of an sRGB colour (0..255 channels)."""
    def linear(c: float) -> float:
        c /= 255.0
        return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4
    r, g, b = (linear(c) for c in rgb)
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def _contrast(a, b) -> float:
    hi, lo = sorted((_luminance(a), _luminance(b)), reverse=True)
    return (hi + 0.05) / (lo + 0.05)


def test20_progress_labels_read_at_4_5_to_1_on_every_fill(page):
    """The progress label is drawn over the bar's fill and over its empty track:
    for every state's fill (every colour stop of a gradient) and the track,
    its colour has a WCAG contrast of at least 4.5:1."""
    page.goto(f"{page.base}/#/jobs")
    page.wait_for_selector("#view table")
    colours = page.evaluate("""async () => {
      const { progressBar } = await import('/static/js/ui.js');
      // the opaque colours in a computed value (a transparent one is no background)
      const rgb = (s) => (s.match(/rgba?\\([^)]*\\)/g) || []).map(
        (c) => c.match(/[\\d.]+/g).map(Number)).filter((c) => c.length === 3 || c[3] > 0)
        .map((c) => c.slice(0, 3));
      const out = {};
      for (const state of ['running', 'queued', 'paused', 'done', 'failed', 'canceled']) {
        const bar = progressBar(0.5, 'label', state, true);
        document.body.append(bar);
        const fill = getComputedStyle(bar.querySelector('.fill'));
        out[state] = { label: rgb(getComputedStyle(bar.querySelector('.label')).color)[0],
                       fills: [...rgb(fill.backgroundImage), ...rgb(fill.backgroundColor)],
                       track: rgb(getComputedStyle(bar).backgroundColor)[0] };
        bar.remove();
      }
      return out;
    }""")
    for state, c in colours.items():
        assert c["fills"], (state, c)
        for background in [*c["fills"], c["track"]]:
            ratio = _contrast(c["label"], background)
            assert ratio >= 4.5, (state, background, round(ratio, 2))


def _exr_of(client, job_id: str, tmp_path) -> dict:
    from renderer import read_exr

    path = tmp_path / f"{job_id}.exr"
    path.write_bytes(client.get(f"/jobs/{job_id}/result.exr").content)
    return read_exr(path)[0]


def test21_the_hdr_viewer_zooms_to_a_pixel_reads_its_value_and_compares_two_jobs(page, tmp_path):
    """The job page's HDR view draws the float data: zoomed in to single
    pixels, the inspector reads the EXR's own value of the pixel under the
    cursor with its standard error (sqrt of var); exposure, display and the
    layers work; compared with another job, the RMSE and relMSE it shows are
    those of the two EXRs."""
    import numpy as np

    body = {"scene": "cornell-box", "method": "path", "spp": 16, "depth": 3, "width": 48,
            "height": 32, "tile_size": 16}
    with api(page.base) as client:
        a, b = (client.post("/jobs", json=dict(body, seed=seed)).json() for seed in (1, 2))
        for job in (a, b):
            assert poll_job(lambda path: client.get(path).json(), job["id"])["status"] == "done"
        exr_a, exr_b = _exr_of(client, a["id"], tmp_path), _exr_of(client, b["id"], tmp_path)
    page.goto(f"{page.base}/#/jobs/{a['id']}")
    page.wait_for_selector("#view .page-head .badge[data-state='done']", timeout=180_000)
    page.click("[data-view='hdr']")
    page.wait_for_selector("#hdr-viewer[data-source='final']")
    assert page.is_hidden("#stage")
    fitted = float(page.get_attribute("#hdr-canvas", "data-scale"))
    box = page.locator("#hdr-canvas").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    for _ in range(12):  # wheel zoom at the cursor: the pixel under it stays under it
        page.mouse.wheel(0, -100)
    scale = float(page.get_attribute("#hdr-canvas", "data-scale"))
    assert scale >= 32 and scale > fitted  # a pixel now spans dozens of screen pixels
    page.mouse.move(cx + 1, cy + 1)
    x = int(page.get_attribute("#hdr-inspector", "data-x"))
    y = int(page.get_attribute("#hdr-inspector", "data-y"))
    assert abs(x - 24) <= 1 and abs(y - 16) <= 1  # the middle of the 48 x 32 image
    for name in "RGB":
        cell = page.locator(f"#hdr-inspector [data-channel='{name}']")
        assert float(cell.get_attribute("data-value")) == float(exr_a[name][y, x])
        assert float(cell.get_attribute("data-stderr")) == pytest.approx(
            float(np.sqrt(exr_a[f"var.{name}"][y, x])), rel=1e-6)
    shot(page, "21-hdr-zoomed")
    # keys: fit, exposure; the other layers and displays
    page.focus("#hdr-canvas")
    page.keyboard.press("f")
    assert float(page.get_attribute("#hdr-canvas", "data-scale")) == pytest.approx(fitted)
    page.keyboard.press("e")
    assert page.text_content("#hdr-exposure-value") == "+0.5 EV"
    page.select_option("#hdr-display", "false")
    page.select_option("#hdr-layer", "normal")  # fetched on demand
    page.wait_for_selector("#hdr-channel option[value='lum']", state="attached")
    page.mouse.move(cx, cy)
    page.wait_for_selector("#hdr-inspector [data-channel='normal.X']")
    page.select_option("#hdr-layer", "rel. error")
    page.select_option("#hdr-layer", "beauty")
    page.select_option("#hdr-display", "srgb")
    # A/B with the other seed: split, then the difference; the figures are the EXRs'
    page.wait_for_selector(f"#hdr-compare option[value='{b['id']}']", state="attached")
    page.select_option("#hdr-compare", b["id"])
    page.wait_for_selector("#hdr-compare-stats[data-rmse]")
    rgb_a = np.stack([exr_a[c] for c in "RGB"], -1).astype(np.float64)
    rgb_b = np.stack([exr_b[c] for c in "RGB"], -1).astype(np.float64)
    d2 = (rgb_a - rgb_b) ** 2
    assert float(page.get_attribute("#hdr-compare-stats", "data-rmse")) == pytest.approx(
        np.sqrt(d2.mean()), rel=1e-5)
    assert float(page.get_attribute("#hdr-compare-stats", "data-relmse")) == pytest.approx(
        (d2 / (rgb_b ** 2 + 0.01)).mean(), rel=1e-5)
    assert page.is_visible("#hdr-split")
    page.fill("#hdr-split", "0.3")
    shot(page, "21-hdr-split")
    page.select_option("#hdr-compare-mode", "diff")
    assert page.is_hidden("#hdr-split")
    shot(page, "21-hdr-difference")


def test22_no_page_scrolls_sideways_on_a_390_px_phone(browser, server):
    """At 390 x 844 (a phone), every page fits its width: the jobs list (its
    table as cards), a job page (with the HDR viewer open), the submit form and
    the workers page, the lab; the job image fits and pinch-zooms (touch-action none)."""
    context = browser.new_context(viewport={"width": 390, "height": 844}, has_touch=True,
                                  is_mobile=True, device_scale_factor=2)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.set_default_timeout(60_000)
    try:
        with api(server) as client:
            job = client.post("/jobs", json={"scene": "cornell-box", "method": "path", "spp": 8,
                                             "depth": 3, "width": 64, "height": 64,
                                             "tile_size": 32}).json()
            assert poll_job(lambda path: client.get(path).json(), job["id"])["status"] == "done"
        page.goto(f"{server}/?token={TEST_ADMIN_TOKEN}")
        page.wait_for_url(f"{server}/")
        widths = {}
        pages = [("jobs", "#/jobs", "#view table"), ("job", f"#/jobs/{job['id']}",
                                                     "#view .page-head .badge[data-state='done']"),
                 ("submit", "#/submit", "#f-method option[value='path-mis']"),
                 ("workers", "#/workers", "#view .panel"),
                 ("experiments", "#/experiments", "#x-methods input[data-method='raster']")]
        for name, hash_, ready in pages:
            page.goto(f"{server}/{hash_}")
            page.wait_for_selector(ready, state="attached")
            if name == "job":
                page.click("[data-view='hdr']")
                page.wait_for_selector("#hdr-viewer[data-source='final']")
                stage = page.locator("#hdr-stage").bounding_box()
                assert stage["x"] >= 0 and stage["x"] + stage["width"] <= 390
                assert page.eval_on_selector("#hdr-stage", "e => getComputedStyle(e).touchAction") \
                    == "none"
            page.wait_for_timeout(200)
            # innerWidth too: a mobile browser zooms out to show a page wider than the screen
            widths[name] = page.evaluate("[document.documentElement.scrollWidth, innerWidth]")
            SHOTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SHOTS / f"22-phone-{name}.png"), full_page=True)
        assert all(scroll <= 390 and inner == 390 for scroll, inner in widths.values()), widths
        assert not errors, errors
    finally:
        context.close()


def test23_a_dropped_connection_shows_a_banner_until_it_is_back(page):
    """With the network gone, the jobs list and a job page say "connection lost
    — data as of HH:MM:SS" and reconnect by themselves when it is back."""
    page.allow_console_error("ERR_INTERNET_DISCONNECTED")
    page.allow_console_error("Failed to load resource")
    page.goto(f"{page.base}/#/jobs")
    page.wait_for_selector("#view table")
    page.wait_for_timeout(500)  # the stream open
    assert page.query_selector("#connection-lost:not([hidden])") is None
    page.context.set_offline(True)
    banner = page.wait_for_selector("#connection-lost:not([hidden])", timeout=20_000)
    text = banner.text_content()
    assert re.fullmatch(r"Connection lost — data as of \d\d:\d\d:\d\d\. Reconnecting…", text), text
    shot(page, "23-connection-lost")
    page.context.set_offline(False)
    page.wait_for_selector("#connection-lost", state="hidden", timeout=30_000)
    assert "offline" not in (page.get_attribute("body", "class") or "")


def test24_run_a_small_experiment_from_the_lab_to_its_table(page):
    """The Lab page's form runs an experiment (path-mis and raster at 2 and 8
    spp, 3 repeats, 32 px); its page follows the jobs, then shows the table
    with the verdicts (raster: biased, inconsistent), the matplotlib figures
    and the CSV link; the list shows it."""
    page.goto(f"{page.base}/#/experiments")
    page.wait_for_selector("#x-methods input[data-method='raster']", state="attached")
    for box in page.query_selector_all("#x-methods input:checked"):
        box.uncheck()
    page.check("#x-methods input[data-method='path-mis']")
    page.check("#x-methods input[data-method='raster']")
    page.fill("#x-spp", "2, 8")
    page.fill("#x-repeats", "3")
    page.fill("#x-size", "32")
    page.fill("#x-depth", "3")
    page.click("#x-submit")
    page.wait_for_url("**/#/experiments/*")
    experiment_id = page.url.rsplit("/", 1)[1]
    page.wait_for_selector("#lab-table", timeout=180_000)
    rows = page.query_selector_all("#lab-table tbody tr")
    assert [(r.get_attribute("data-config"), r.get_attribute("data-spp")) for r in rows] == [
        ("path-mis", "2"), ("path-mis", "8"), ("raster", "2"), ("raster", "8")]
    verdicts = "els => els.map(e => e.dataset.verdict)"
    first = page.locator("#lab-table tr[data-config='raster'][data-spp='2'] [data-verdict]")
    assert first.evaluate_all(verdicts)[1:] == ["no", "no"]  # biased, inconsistent
    last = page.locator("#lab-table tr[data-config='raster'][data-spp='8'] [data-verdict]")
    assert last.evaluate_all(verdicts) == ["no"]  # its bias test at 8 spp
    path = page.locator("#lab-table tr[data-config='path-mis'][data-spp='2'] [data-verdict]")
    assert path.evaluate_all(verdicts)[1:] == ["yes", "yes"]
    for image in ("#lab-plot", "#lab-maps"):
        page.wait_for_function(f"document.querySelector('{image}').naturalWidth > 0")
    assert page.get_attribute("#x-csv", "href") == f"/experiments/{experiment_id}/report.csv"
    shot(page, "24-lab-experiment")
    page.goto(f"{page.base}/#/experiments")
    page.wait_for_selector(f"#experiments-table tr[data-experiment='{experiment_id}']")
    shot(page, "24-lab-list")


def test25_jobs_ticked_on_the_list_plot_together_and_against_a_reference(page):
    """Done jobs ticked on the jobs list open a comparison: their convergence
    curves on one plot (against samples and against time); marking one as the
    reference plots the others' true RMSE against it, the figures the API's."""
    body = {"scene": "cornell-box", "method": "path", "spp": 32, "depth": 3, "width": 32,
            "height": 32, "tile_size": 16}
    with api(page.base) as client:
        ids = [client.post("/jobs", json=dict(body, seed=seed, sampler=sampler)).json()["id"]
               for seed, sampler in ((1, "sobol"), (2, "random"))]
        ref = client.post("/jobs", json=dict(body, spp=1024, seed=3, progressive=False)).json()["id"]
        for job_id in ids + [ref]:
            assert poll_job(lambda path: client.get(path).json(), job_id)["status"] == "done"
        expected = client.get("/compare", params={"jobs": ",".join(ids + [ref]),
                                                  "reference": ref}).json()
    page.goto(f"{page.base}/#/jobs")
    for job_id in ids + [ref]:
        page.check(f"#jobs-table input[data-select='{job_id}']")
    assert page.text_content("#compare-jobs") == "Compare (3)"
    page.click("#compare-jobs")
    page.wait_for_selector("#compare-table")
    assert page.locator("#plot-samples svg .series").count() == 3  # error statistics
    assert page.locator("#plot-seconds svg .series").count() == 3
    page.check(f"input[data-reference='{ref}']")
    page.wait_for_url(f"**reference={ref}")
    page.wait_for_selector(f"#compare-table tr[data-job='{ids[0]}'] td[data-rmse]:not([data-rmse=''])")
    for job in expected["jobs"][:2]:
        shown = page.get_attribute(f"#compare-table tr[data-job='{job['id']}'] td[data-rmse]", "data-rmse")
        assert float(shown) == pytest.approx(job["points"][-1]["rmse"], rel=1e-9)
    # RMSE curves: the two jobs (the reference against itself is 0, not drawn)
    assert page.locator("#plot-samples svg .series").count() == 2
    shot(page, "25-compare-jobs")
    assert page.get_attribute("#compare-png", "href").startswith("/compare.png?jobs=")


def test26_the_lab_and_compare_pages_fit_a_phone(browser, server):
    """At 390 x 844, an experiment's page (its report table as cards, its
    figures scaled down) and a comparison of jobs fit the screen's width."""
    with api(server) as client:
        experiment = client.post("/experiments", json={
            "scene": "cornell-box", "width": 16, "height": 16, "depth": 3, "repeats": 2,
            "spp": [2, 4], "configs": [{"method": "path-mis"}, {"method": "raster"}]}).json()
        wait_for(lambda: client.get(f"/experiments/{experiment['id']}").json()["status"] == "done",
                 180, "the experiment to finish", interval=0.5)
        jobs = [run["job"] for run in experiment["runs"][:2]] + [experiment["reference_job"]]
    context = browser.new_context(viewport={"width": 390, "height": 844}, has_touch=True,
                                  is_mobile=True, device_scale_factor=2)
    page = context.new_page()
    page.set_default_timeout(60_000)
    try:
        page.goto(f"{server}/?token={TEST_ADMIN_TOKEN}")
        page.wait_for_url(f"{server}/")
        widths = {}
        for name, hash_, ready in (
                ("experiment", f"#/experiments/{experiment['id']}", "#lab-maps"),
                ("compare", f"#/compare?jobs={','.join(jobs)}&reference={jobs[-1]}",
                 "#plot-samples svg")):
            page.goto(f"{server}/{hash_}")
            page.wait_for_selector(ready)
            page.wait_for_timeout(200)
            widths[name] = page.evaluate("[document.documentElement.scrollWidth, innerWidth]")
            SHOTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SHOTS / f"26-phone-{name}.png"), full_page=True)
        assert all(scroll <= 390 and inner == 390 for scroll, inner in widths.values()), widths
    finally:
        context.close()


def test27_a_login_link_from_another_site_asks_before_it_logs_in(anon_page, other_origin):
    """Login CSRF: a page of another origin links to the service's login URL with
    someone else's token. Following it logs nobody in: the dashboard takes the
    token out of the address bar and asks, naming whose link it is; only a
    click on that page logs in. (The printed URL, opened from outside any
    page, logs in at once: test09.)"""
    page = anon_page
    with api(page.base) as client:
        client.post("/users", json={"name": "mallory", "role": "artist"})  # 201, or 409 on a rerun
        secret = client.post("/tokens", json={"user": "mallory", "label": "a link"}).json()["token"]
    other = page.context.new_page()  # the same browser; `page` must not visit another host

    def follow_the_link():
        other.goto(f"{other_origin}/")
        other.evaluate("""url => { const a = document.createElement('a'); a.id = 'go';
            a.href = url; a.textContent = 'free renders'; document.body.append(a); }""",
                       f"{page.base}/?token={secret}")
        other.click("#go")
        other.wait_for_selector("#link-form")

    follow_the_link()
    assert other.url == f"{page.base}/#/login?link=1"  # the token left the address bar
    assert other.inner_text("#link-user-name") == "mallory"
    assert "another site" in other.inner_text("#link-why")
    assert "rayfarm_session" not in cookies_of(page)  # nobody is logged in yet
    shot(other, "27-login-link-asks")
    # Cancel: still nobody.
    other.click("#link-cancel")
    other.wait_for_selector("#login-form")
    assert "rayfarm_session" not in cookies_of(page)
    # Following it again and saying yes logs in as the link's user, as it says.
    follow_the_link()
    other.wait_for_selector("#link-login:not([disabled])")
    assert other.inner_text("#link-login") == "Log in as mallory"
    other.click("#link-login")
    other.wait_for_url(f"{page.base}/#/jobs")
    other.wait_for_selector("#whoami-user")
    assert other.inner_text("#whoami-user") == "mallory"
    assert "rayfarm_session" in cookies_of(page)
    other.close()
