"""Shared fixtures of the service and farm tests: real parts, tiny renders.

- `local_client`: one embedded-mode service (FastAPI + scheduler + local
  process pool) for the whole session; Numba kernels load once per process.
- `redis_url`: a real Redis that this test run started itself (`redis-server`
  on a free port, nothing kept on disk), flushed per test; a developer's own
  Redis on 6379 is never touched.
- `spawn_worker` / `spawn_serve`: `rayfarm worker` / `rayfarm serve` as child
  processes in their own process groups, killed (the whole group) afterwards.
- `embedded_serve`: one `rayfarm serve` child in embedded mode (no broker:
  SQLite, a local pool of 2) per test module; yields (child, base URL).
- `reference_channels`: an undisturbed render of a job body, in this process.
- `real_scenes()`: the folder of the shared Mitsuba research scenes, which
  never enter the repository ($RAYFARM_REAL_SCENES, else ../shared/scenes/real
  beside the checkout); a test that needs them is skipped where they are not.
- `postgres_server` / `postgres_url`: a PostgreSQL cluster this test run
  initialised and started itself (Debian's `initdb`/`pg_ctl`, a tmp data dir,
  a free port, its socket in tmp), stopped at the end; `postgres_url` is a
  fresh database per test. A server already running here is never touched.

Authentication is on, as in production: every service a test starts has the
admin token `TEST_ADMIN_TOKEN` (RAYFARM_ADMIN_TOKEN), the test process and its
children find it in RAYFARM_TOKEN (the client and CLI read it), `local_client`
sends it, and `ADMIN_HEADERS` carries it for plain httpx calls. `make_user`
adds users of other roles with tokens of their own.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# The renderer's on-disk caches (radiosity solutions) go to a directory of this
# run, not the user's ~/.cache; child processes (pools, workers) inherit it.
if "RAYFARM_CACHE_DIR" not in os.environ:
    import tempfile

    import atexit

    os.environ["RAYFARM_CACHE_DIR"] = tempfile.mkdtemp(prefix="rayfarm-test-cache-")
    atexit.register(shutil.rmtree, os.environ["RAYFARM_CACHE_DIR"], ignore_errors=True)
# The admin token of every service the tests start (see the module doc).
TEST_ADMIN_TOKEN = "rf_test-admin-" + secrets.token_urlsafe(24)
os.environ["RAYFARM_TOKEN"] = TEST_ADMIN_TOKEN  # what clients and the CLI send
os.environ["RAYFARM_ADMIN_TOKEN"] = TEST_ADMIN_TOKEN  # what every Settings() here bootstraps
# The names in-process clients use (TestClient's own, and a "browser" of test_service_auth);
# a `rayfarm serve` child is reached as 127.0.0.1, which every service answers to.
os.environ["RAYFARM_ALLOWED_HOSTS"] = "testserver,farm.test"
ADMIN_HEADERS = {"Authorization": f"Bearer {TEST_ADMIN_TOKEN}"}
TINY = {"scene": "cornell-box", "method": "path", "spp": 4, "depth": 3, "tile_size": 8,
        "seed": 7, "width": 32, "height": 32}
# The shared Mitsuba research scenes are never copied into the repository.
REAL_SCENES_DEFAULT = ROOT.parent / "shared" / "scenes" / "real"


def real_scenes(*required: str) -> Path:
    """The folder of the shared real scenes: $RAYFARM_REAL_SCENES, else
    ../shared/scenes/real beside the checkout. Skips the calling test when
    that folder, or any `required` path inside it (`"veach-bidir/scene.xml"`),
    is missing, naming both places it looks."""
    configured = os.environ.get("RAYFARM_REAL_SCENES")
    folder = Path(configured).expanduser() if configured else REAL_SCENES_DEFAULT
    missing = [name for name in required if not (folder / name).exists()]
    if not folder.is_dir() or missing:
        what = f"{', '.join(missing)} not in {folder}" if folder.is_dir() else f"no folder {folder}"
        source = " (from RAYFARM_REAL_SCENES)" if configured else ""
        pytest.skip(f"the shared real scenes are missing: {what}{source}; set RAYFARM_REAL_SCENES "
                    f"to their folder, or put them at {REAL_SCENES_DEFAULT} (the default, "
                    "../shared/scenes/real beside the checkout)")
    return folder


def zip_of_folder(folder: Path, out_dir: Path) -> Path:
    """`folder` zipped as `zip -r NAME.zip NAME` packs it (every file under
    NAME/), written to out_dir/NAME.zip; returns its path."""
    return Path(shutil.make_archive(str(out_dir / folder.name), "zip", root_dir=folder.parent,
                                    base_dir=folder.name))


def wait_for(predicate: Callable[[], object], timeout: float, what: str, interval: float = 0.05):
    """Poll `predicate` until it returns something truthy; fail after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


def rayfarm_command() -> list[str]:
    """The `rayfarm` console script of this interpreter's environment."""
    script = Path(sys.executable).parent / "rayfarm"
    if script.exists():
        return [str(script)]
    found = shutil.which("rayfarm")
    if found is None:
        pytest.fail("the rayfarm console script is not installed (pip install -e .)")
    return [found]


def poll_job(get_json: Callable[[str], dict], job_id: str, timeout: float = 300.0) -> dict:
    """Poll GET /jobs/{id} until the job is final; returns it. The timeout is
    generous: after a renderer edit, Numba recompiles in every fresh process."""
    def final():
        job = get_json(f"/jobs/{job_id}")
        return job if job["status"] in ("done", "failed", "canceled") else None
    return wait_for(final, timeout, f"job {job_id} to finish")


def channels_of(exr_path: Path) -> dict[str, np.ndarray]:
    from renderer import read_exr

    channels, _header = read_exr(exr_path)
    return channels


def assert_bit_identical(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    """Every channel the same bytes: beauty, var, and the AOVs (film.py)."""
    assert set(a) == set(b) and {"R", "G", "B", "var.R", "var.G", "var.B", "samples.Y"} <= set(a)
    for name in sorted(a):
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        assert a[name].tobytes() == b[name].tobytes(), f"channel {name} differs"



def assert_denoised_beside_raw(exr_path: Path, raw: dict[str, np.ndarray]) -> None:
    """A denoised job's EXR: the raw channels bit-identical to `raw` (the same
    job without denoise), denoised.R/G/B beside them, finite and not the raw
    image, and the header saying so."""
    from renderer import read_exr

    channels, header = read_exr(exr_path)
    assert {"denoised.R", "denoised.G", "denoised.B"} | set(raw) == set(channels)
    assert_bit_identical({k: v for k, v in channels.items() if not k.startswith("denoised.")},
                         raw)
    denoised = np.stack([channels[f"denoised.{c}"] for c in "RGB"], axis=-1)
    assert np.all(np.isfinite(denoised)) and denoised.shape == raw["R"].shape + (3,)
    assert not np.array_equal(denoised[..., 0], raw["R"])
    assert header["rayfarm.denoised"] == 1


def assert_equals_renderer(exr_path: Path, body: dict) -> None:
    """The EXR is the renderer's own in-process run of the job body's DAG
    (`render_serial`), bit for bit, mean and var channels."""
    from renderer import RenderSpec, load_scene, render_serial

    got = channels_of(exr_path)
    spec = RenderSpec(**{k: v for k, v in body.items() if k not in ("scene", "progressive")})
    film = render_serial(load_scene(body["scene"]), spec)
    mean = film.mean().astype(np.float32)
    var = film.variance_of_mean().astype(np.float32)
    for c, name in enumerate("RGB"):
        assert got[name].tobytes() == np.ascontiguousarray(mean[..., c]).tobytes(), name
        assert got[f"var.{name}"].tobytes() == np.ascontiguousarray(var[..., c]).tobytes(), name

def pytest_sessionstart(session):
    """Every kernel compiled into Numba's on-disk cache before the first test,
    two method families at a time on a cold cache (renderer.runtime.warm_up):
    the worker and service processes the tests start then only load it. Left
    to themselves, each Celery render process compiled every kernel on its
    own for minutes while its worker held prefetched units.

    Under pytest-xdist (pyproject's addopts) this runs in the controller,
    before it starts its workers (xdist does that in its own, later
    sessionstart hook), so the workers only load the cache. It is outside
    every test, so no test's timeout counts a cold compile: as a session
    fixture, a compile slowed down by a loaded machine timed out the waiting
    worker's setup and with it every test of that worker."""
    if hasattr(session.config, "workerinput") or session.config.option.collectonly:
        return
    from renderer import warm_up

    warm_up(processes=2)


# -- the embedded service ---------------------------------------------------------

@pytest.fixture(scope="session")
def local_settings(tmp_path_factory):
    from service.settings import Settings

    return Settings(data_dir=tmp_path_factory.mktemp("local-farm"), broker_url="",
                    database_url="", local_workers=2, poll_interval=0.05,
                    admin_token=TEST_ADMIN_TOKEN)


@pytest.fixture(scope="session")
def local_app(local_settings):
    """The embedded service's app, started (lifespan entered) for the session."""
    from fastapi.testclient import TestClient

    from service.main import create_app

    app = create_app(local_settings)
    with TestClient(app):
        yield app


@pytest.fixture(scope="session")
def local_client(local_app):
    """A client of the embedded service, logged in as the admin (bearer token).
    Not entered as a context manager: that would run the app's lifespan a second
    time, a second scheduler and pool on the same ledger."""
    from fastapi.testclient import TestClient

    client = TestClient(local_app, headers=ADMIN_HEADERS)
    yield client
    client.close()


@pytest.fixture(scope="session")
def make_user(local_app):
    """make_user(name, role="artist") -> a TestClient of the embedded service
    holding a fresh token of that (new or existing) user."""
    from fastapi.testclient import TestClient

    from service import auth
    from service.models import User, utcnow

    sessions = local_app.state.farm.sessions

    def make(name: str, role: str = "artist") -> TestClient:
        with sessions.begin() as session:
            if session.get(User, name) is None:
                auth.add_user(session, name, role, utcnow())
            _, secret = auth.create_token(session, name, utcnow(), label="test")
        client = TestClient(local_app, headers={"Authorization": f"Bearer {secret}"})
        client.token = secret
        return client

    return make


# -- reference renders ---------------------------------------------------------------

@pytest.fixture(scope="session")
def reference_channels(tmp_path_factory):
    """Render a job body undisturbed, in this process, through plan -> units ->
    merge; returns its EXR channels as read back from disk."""
    from renderer import build_scene, merge, plan, resolve_document, run_unit

    cache: dict[str, dict] = {}
    out_dir = tmp_path_factory.mktemp("reference")

    def render(body: dict) -> dict[str, np.ndarray]:
        key = repr(sorted(body.items()))
        if key not in cache:
            doc = resolve_document(body["scene"], allow_files=False)
            spec = spec_of(body)
            scene = build_scene(doc)
            film = merge(spec.width, spec.height,
                         [run_unit(scene, spec, u) for u in plan(spec)])
            path = out_dir / f"ref-{len(cache)}.exr"
            film.write_exr(path)
            cache[key] = channels_of(path)
        return cache[key]

    return render


def submit(client, body: dict) -> dict:
    """POST /jobs, expecting 201 and a Location header; returns the job."""
    response = client.post("/jobs", json=body)
    assert response.status_code == 201, response.text
    assert response.headers["location"] == f"/jobs/{response.json()['id']}"
    return response.json()


def spec_of(body: dict):
    """The RenderSpec of a job body (the scene's camera size unless it gives one)."""
    from renderer import RenderSpec, resolve_document

    doc = resolve_document(body["scene"], allow_files=False)
    return RenderSpec(method=body["method"], spp=body["spp"], depth=body["depth"],
                      width=body.get("width", doc["camera"]["width"]),
                      height=body.get("height", doc["camera"]["height"]),
                      tile_size=body.get("tile_size", 64), seed=body.get("seed", 0),
                      sampler=body.get("sampler", RenderSpec().sampler)).validate()


def planned_units(body: dict) -> int:
    """The units a tile method's job body is planned into (progressive unless
    it says not): TINY's three passes are one unit each (renderer.plan)."""
    from renderer.plan import count_units

    return count_units(spec_of(body), body.get("progressive", True))


def assert_complete_progress(progress: dict, *, units: int, samples: int) -> None:
    """A done job's progress: every unit and sample counted, nothing left."""
    assert progress["units_done"] == progress["units_total"] == units, progress
    assert progress["samples_done"] == progress["samples_total"] == samples, progress
    assert progress["fraction"] == 1.0 and progress["eta"] == 0.0, progress
    assert progress["elapsed"] is not None and progress["elapsed"] >= 0, progress


def get_json(client):
    """A GET that expects 200 and returns the JSON body (for poll_job)."""
    def get(path: str) -> dict:
        response = client.get(path)
        assert response.status_code == 200, response.text
        return response.json()
    return get


# -- the real farm: Redis and child processes ---------------------------------------------

@pytest.fixture(scope="session")
def redis_server(tmp_path_factory):
    """A `redis-server` of this test run on a free port of 127.0.0.1 (no
    persistence), stopped at the end; yields its URL without a database."""
    import redis

    binary = shutil.which("redis-server")
    if binary is None:
        message = "no redis-server on PATH (apt-get install redis-server; .ci/run does)"
        if os.environ.get("CI"):  # .ci/run installs it: its absence is a failure there
            pytest.fail(message)
        pytest.skip(message)
    directory = tmp_path_factory.mktemp("redis")
    port = free_port()
    proc = subprocess.Popen([binary, "--port", str(port), "--bind", "127.0.0.1", "--save", "",
                             "--appendonly", "no", "--dir", str(directory),
                             "--logfile", str(directory / "redis.log")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    url = f"redis://127.0.0.1:{port}"
    client = redis.Redis.from_url(url)

    def answers():
        if proc.poll() is not None:
            pytest.fail(f"redis-server exited: {(directory / 'redis.log').read_text()}")
        try:
            return client.ping()
        except redis.RedisError:
            return False
    try:
        wait_for(answers, 30, "redis-server to answer")
        yield url
    finally:
        client.close()
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


@pytest.fixture
def redis_url(redis_server):
    """Database 0 of this run's own Redis, empty at the start and end of the test."""
    import redis

    url = f"{redis_server}/0"
    client = redis.Redis.from_url(url)
    client.flushdb()
    yield url
    client.flushdb()
    client.close()


def _postgres_binaries() -> Path | None:
    """The newest of Debian's PostgreSQL bin directories (initdb, pg_ctl), if any."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"),
                   key=lambda p: int(p.parent.parent.name) if p.parent.parent.name.isdigit() else 0)
    if found:
        return found[-1].parent
    initdb = shutil.which("initdb")
    return Path(initdb).parent if initdb else None


@pytest.fixture(scope="session")
def postgres_server():
    """A PostgreSQL cluster of this test run on a free port of 127.0.0.1 (its
    unix socket in a tmp dir too, fsync off), stopped at the end; yields the
    URL of its `postgres` database (superuser `postgres`, trust auth)."""
    bindir = _postgres_binaries()
    if bindir is None:
        message = "no PostgreSQL binaries (apt-get install postgresql; .ci/run does)"
        if os.environ.get("CI"):  # .ci/run installs it: its absence is a failure there
            pytest.fail(message)
        pytest.skip(message)
    import psycopg

    import tempfile

    # Not under pytest's tmp tree: that is private to root, and the cluster's
    # owner (below) must reach its directory.
    directory = Path(tempfile.mkdtemp(prefix="rayfarm-test-pg-"))
    data, sockets, log = directory / "data", directory / "run", directory / "postgres.log"
    sockets.mkdir()
    # initdb refuses to run as root: then the cluster belongs to the `postgres` user.
    as_owner: list[str] = []
    if os.getuid() == 0:
        import pwd

        owner = pwd.getpwnam("postgres")
        for path in (directory, sockets):
            os.chown(path, owner.pw_uid, owner.pw_gid)
        as_owner = ["setpriv", f"--reuid={owner.pw_uid}", f"--regid={owner.pw_gid}",
                    "--init-groups", "--"]
    subprocess.run([*as_owner, str(bindir / "initdb"), "-D", str(data), "-U", "postgres",
                    "--auth=trust", "--no-sync", "-E", "UTF8", "--locale=C"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    port = free_port()
    options = (f"-p {port} -h 127.0.0.1 -k {sockets} -c fsync=off -c synchronous_commit=off "
               "-c full_page_writes=off -c max_connections=200")
    subprocess.run([*as_owner, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(log),
                    "-o", options, "-w", "-t", "60", "start"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    url = f"postgresql://postgres@127.0.0.1:{port}/postgres"
    try:
        def answers():
            try:
                with psycopg.connect(url, connect_timeout=2):
                    return True
            except psycopg.Error:
                return False
        wait_for(answers, 60, "postgres to answer", interval=0.2)
        yield url
    finally:
        subprocess.run([*as_owner, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate",
                        "-w", "-t", "60", "stop"],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        shutil.rmtree(directory, ignore_errors=True)


@pytest.fixture
def postgres_url(postgres_server):
    """A fresh, empty database of this run's own PostgreSQL, dropped after the
    test; its URL (plain `postgresql://`: Settings adds the driver)."""
    import psycopg

    name = f"rayfarm_test_{secrets.token_hex(5)}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    yield postgres_server.rsplit("/", 1)[0] + f"/{name}"
    with psycopg.connect(postgres_server, autocommit=True) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


class Child:
    """A child process in its own process group, with its output in a log file."""

    def __init__(self, args: list[str], env: dict, log_path: Path):
        self.log_path = log_path
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen(args, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True, cwd=ROOT)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def kill_group(self, sig: int = signal.SIGKILL) -> None:
        """Signal the whole process group (a prefork worker and its children)."""
        try:
            os.killpg(self.proc.pid, sig)
        except ProcessLookupError:
            pass

    def group_alive(self) -> bool:
        """Does any process of the group still exist?"""
        try:
            os.killpg(self.proc.pid, 0)
        except ProcessLookupError:
            return False
        return True

    def stop(self, timeout: float = 20.0) -> None:
        if self.proc.poll() is None:
            self.kill_group(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                pass
        self.kill_group(signal.SIGKILL)  # stragglers of the group, if any
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
        self._log.close()


def farm_env(redis_url: str, **extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    env.update({"RAYFARM_BROKER_URL": redis_url, "PYTHONUNBUFFERED": "1",
                "RAYFARM_ADMIN_TOKEN": TEST_ADMIN_TOKEN, "RAYFARM_TOKEN": TEST_ADMIN_TOKEN,
                **extra})
    return env


@pytest.fixture
def spawn_worker(redis_url, tmp_path):
    """Start `rayfarm worker` processes; each is stopped (whole group) at teardown."""
    children: list[Child] = []

    def spawn(concurrency: int = 2, name: str | None = None, **env: str) -> Child:
        log = tmp_path / f"worker-{len(children)}.log"
        child = Child([*rayfarm_command(), "worker", "--concurrency", str(concurrency),
                       "--loglevel", "info", *(["--name", name] if name else [])],
                      farm_env(redis_url, **env), log)
        children.append(child)
        wait_for(lambda: " ready." in child.log() or child.proc.poll() is not None, 120,
                 "the worker to be ready")
        assert child.proc.poll() is None, f"worker exited:\n{child.log()}"
        return child

    yield spawn
    for child in children:
        child.stop()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_healthy(child: Child, base: str) -> None:
    """Wait until the `rayfarm serve` child answers /healthz with 200 (the first
    start after a renderer edit compiles the kernels: minutes)."""
    import httpx

    def healthy():
        if child.proc.poll() is not None:
            pytest.fail(f"rayfarm serve exited:\n{child.log()}")
        try:
            return httpx.get(f"{base}/healthz", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False
    wait_for(healthy, 300, "rayfarm serve to be healthy", interval=0.2)


def embedded_env(data_dir: Path, **extra: str | None) -> dict:
    """The environment of a `rayfarm serve` child in embedded mode: this
    process's without any RAYFARM_ setting, then the data dir, a 0.05 s tick,
    two render processes, unbuffered output and the tests' admin token;
    `extra` adds or overrides settings (None removes one)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    env.update(RAYFARM_DATA_DIR=str(data_dir), RAYFARM_POLL_INTERVAL="0.05",
               RAYFARM_LOCAL_WORKERS="2", PYTHONUNBUFFERED="1",
               RAYFARM_ADMIN_TOKEN=TEST_ADMIN_TOKEN, RAYFARM_TOKEN=TEST_ADMIN_TOKEN)
    for key, value in extra.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return env


def start_serve(env: dict, log: Path) -> tuple[Child, str]:
    """`rayfarm serve` with `env` on a free port of 127.0.0.1, once it is
    healthy: (child, base URL). The caller stops the child (`Child.stop`)."""
    port = free_port()
    child = Child([*rayfarm_command(), "serve", "--host", "127.0.0.1", "--port", str(port)],
                  env, log)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_healthy(child, base)
    except BaseException:
        child.stop()
        raise
    return child, base


@pytest.fixture
def spawn_serve(redis_url, tmp_path):
    """Start `rayfarm serve` on a free port; returns (child, base_url)."""
    children: list[Child] = []

    def spawn(**env: str) -> tuple[Child, str]:
        child, base = start_serve(
            farm_env(redis_url, RAYFARM_DATA_DIR=str(tmp_path / "serve-data"), **env),
            tmp_path / f"serve-{len(children)}.log")
        children.append(child)
        return child, base

    yield spawn
    for child in children:
        child.stop()


@pytest.fixture(scope="module")
def embedded_serve(tmp_path_factory):
    """`rayfarm serve` in embedded mode (no RAYFARM_BROKER_URL: SQLite ledger, a
    local pool of 2 processes, a 0.05 s scheduler tick), once per test module;
    yields (child, base URL), stops the child's process group afterwards and
    then fails if the service logged a traceback meanwhile."""
    directory = tmp_path_factory.mktemp("embedded-serve")
    child, base = start_serve(embedded_env(directory / "data"), directory / "serve.log")
    try:
        yield child, base
    finally:
        child.stop()
    assert child.proc.returncode is not None
    assert "Traceback" not in child.log(), child.log()
