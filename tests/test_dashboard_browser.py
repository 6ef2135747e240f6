"""The dashboard in a real headless Chromium (Debian's, at /usr/bin/chromium,
driven by Playwright) against a real `rayfarm serve` in embedded mode.

Every test saves screenshots to test-artifacts/screenshots/ and fails if the
page throws, logs an error, or requests anything from another host (the
dashboard must work offline).
"""

from __future__ import annotations

import os
from pathlib import Path

import httpx
import pytest

from conftest import ROOT, wait_for

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
def page(browser, server, request):
    """A fresh page (1440 x 900, a laptop screen) whose problems fail the test."""
    context = browser.new_context(viewport={"width": 1440, "height": 900})
    page = context.new_page()
    problems: list[str] = []
    page.on("pageerror", lambda exc: problems.append(f"page error: {exc}"))
    page.on("console", lambda msg: problems.append(f"console {msg.type}: {msg.text}")
            if msg.type == "error" and "422" not in msg.text else None)
    page.on("request", lambda req: problems.append(f"request to another host: {req.url}")
            if not req.url.startswith((server, "data:", "blob:")) else None)
    page.set_default_timeout(60_000)
    page.base = server
    yield page
    context.close()
    assert not problems, problems


def shot(page, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def api(server: str):
    return httpx.Client(base_url=server, timeout=30)


def progress_value(page) -> int:
    return int(page.get_attribute("#view .progress.big", "aria-valuenow"))


def test01_submit_through_the_form_then_watch_progress_and_preview_change(page):
    page.goto(f"{page.base}/#/submit")
    page.wait_for_selector("#f-method option[value='path-mis']", state="attached")
    page.wait_for_selector("#f-scene option[value='cornell-box']", state="attached")
    page.select_option("#f-scene", "cornell-box")
    page.select_option("#f-method", "path-mis")
    page.wait_for_selector("#f-opt-heuristic")  # the method's options come from GET /methods
    page.select_option("#f-sampler", "sobol")
    for name, value in (("spp", "1024"), ("depth", "5"), ("width", "128"), ("height", "128"),
                        ("tile_size", "32"), ("seed", "5")):
        page.fill(f"#f-{name}", value)
    shot(page, "01-submit-form")
    page.click("#submit-button")
    page.wait_for_url("**/#/jobs/*")
    job_id = page.url.rsplit("/", 1)[1]
    with api(page.base) as client:
        job = client.get(f"/jobs/{job_id}").json()
    assert (job["spp"], job["width"], job["sampler"], job["method"]) == (1024, 128, "sobol", "path-mis")

    # The preview appears and changes as passes land; the progress bar advances.
    page.wait_for_selector("#stage img#preview[data-loaded]")
    first = page.locator("#stage").screenshot()
    first_src = page.get_attribute("#stage img#preview", "src")
    values = {progress_value(page)}
    shot(page, "02-job-running")
    page.wait_for_function(
        "src => { const img = document.querySelector('#stage img#preview');"
        " return img && img.dataset.loaded && img.getAttribute('src') !== src; }", arg=first_src)
    assert page.locator("#tile-map .tile").count() == 16  # 4 x 4 tiles of 32 px
    wait_for(lambda: values.add(progress_value(page)) or len(values - {100}) >= 2, 120,
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
