"""The client side: `service.client` and the `rayfarm submit|watch|fetch|jobs|cancel|workers`
commands, against one real `rayfarm serve` child in embedded mode (module-scoped).

The CLI runs as the installed console script (a subprocess); images are read
back from disk. To catch a job between planned and rendered, a `blocker`
(a big job at the highest priority) keeps the local pool busy: later jobs are
planned at once but none of their units is enqueued until it is canceled.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from conftest import (ADMIN_HEADERS, ROOT, TEST_ADMIN_TOKEN, TINY, assert_bit_identical,
                      channels_of, free_port, planned_units, rayfarm_command, real_scenes,
                      wait_for, zip_of_folder)
from service.client import (Conflict, Invalid, NotFound, RayfarmClient, ServerSentEvent,
                            ServerUnavailable, parse_sse)

TINY_ARGS = ["cornell-box", "--method", "path", "--spp", "4", "--depth", "3", "--tile-size", "8",
             "--seed", "7", "--width", "32", "--height", "32"]
JOB_ID = re.compile(r"[0-9a-f]{12}")


def cli(*args: str, server: str | None, env: dict | None = None, timeout: float = 120,
        cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """Run the `rayfarm` console script with `--server` (unless None)."""
    base_env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
    base_env["RAYFARM_TOKEN"] = TEST_ADMIN_TOKEN
    command = [*rayfarm_command(), *args] + (["--server", server] if server else [])
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env={**base_env, **(env or {})})


def assert_clean_failure(out: subprocess.CompletedProcess, code: int, *words: str) -> None:
    """Exit `code`, nothing on stdout, `words` on stderr, no traceback."""
    assert out.returncode == code, (out.returncode, out.stdout, out.stderr)
    assert out.stdout == "", out.stdout
    assert "Traceback" not in out.stderr, out.stderr
    for word in words:
        assert word in out.stderr, out.stderr


@pytest.fixture(scope="module")
def server(embedded_serve) -> str:
    return embedded_serve[1]


@pytest.fixture
def client(server):
    with RayfarmClient(server, timeout=30) as farm:
        yield farm


@pytest.fixture(scope="module")
def tiny_job(server) -> tuple[str, subprocess.CompletedProcess]:
    """TINY submitted once through `rayfarm submit`: (job id, the finished process)."""
    out = cli("submit", *TINY_ARGS, server=server)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip(), out


@contextmanager
def blocker(farm: RayfarmClient):
    """A job of 64 units of about a second each at the highest priority, running;
    canceled on exit (if still active)."""
    job = farm.submit(**dict(TINY, width=128, height=128, spp=4096, tile_size=16,
                             progressive=False, priority=100))
    try:
        wait_for(lambda: farm.job(job["id"])["status"] == "running", 60, "the blocker to run")
        yield job
    finally:
        try:
            farm.cancel(job["id"])
        except Conflict:
            pass


def blocked_job(farm: RayfarmClient, **fields) -> dict:
    """Submit TINY (with `fields`) behind a running blocker; returns it once planned."""
    job = farm.submit(**dict(TINY, **fields))
    wait_for(lambda: farm.units(job["id"]), 60, f"job {job['id']} to be planned")
    job = farm.job(job["id"])
    assert job["status"] == "running" and job["progress"]["units_done"] == 0, job
    return job


class CuttableProxy:
    """A TCP forwarder to the service whose connections can be cut, as a network
    drop would; `close()` also stops listening (reconnecting is refused)."""

    def __init__(self, target: str):
        self.target = ("127.0.0.1", int(target.rsplit(":", 1)[1]))
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.1)
        self.url = f"http://127.0.0.1:{self.listener.getsockname()[1]}"
        self.sockets: list[socket.socket] = []
        self.closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.closed:
            try:
                down, _ = self.listener.accept()
            except OSError:  # timeout, or closed
                continue
            up = socket.create_connection(self.target)
            self.sockets += [down, up]
            for src, dst in ((down, up), (up, down)):
                threading.Thread(target=self._pump, args=(src, dst), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass

    def cut(self) -> None:
        for sock in self.sockets:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        self.sockets = []

    def close(self) -> None:
        self.closed = True
        self.listener.close()
        self.cut()


# -- the event-stream parser ---------------------------------------------------------

def test01_sse_parser_follows_the_event_stream_rules():
    lines = ["retry: 2000", "", ": keep-alive", "",
             "id: 7", "event: job", "data: {\"a\":", "data:  1}", "",  # one space stripped
             "data:no-space", "", "event: empty", "",  # no data: never dispatched
             "event: x", "data", "data: ", "", "unknown: field", "retry: soon",
             "retry: \u00b2",  # "²".isdigit(), but not a number: ignored like "soon"
             "data: tail-without-blank-line"]
    assert list(parse_sse(lines)) == [
        2000,
        ServerSentEvent("job", '{"a":\n 1}', "7"),
        ServerSentEvent("message", "no-space", "7"),
        ServerSentEvent("x", "\n", "7"),
    ]


# -- the CLI -------------------------------------------------------------------------------

def test02_submit_prints_only_the_job_id(tiny_job, client):
    job_id, out = tiny_job
    assert JOB_ID.fullmatch(job_id) and out.stdout == job_id + "\n", out.stdout
    assert job_id in out.stderr and "Traceback" not in out.stderr
    job = client.job(job_id)
    assert {k: job[k] for k in TINY} == dict(TINY, method="path-mis"), job  # the alias resolved
    assert job["sampler"] == "sobol" and job["progressive"] is True  # the defaults


def test03_submit_passes_every_option(server, client):
    out = cli("submit", *TINY_ARGS, "--sampler", "sobol", "--priority", "-5", "--no-progressive",
              "--option", "heuristic=balance", "--method", "path-mis", "--denoise",
              server=server)
    assert out.returncode == 0, out.stderr
    job = client.job(out.stdout.strip())
    assert (job["sampler"], job["priority"], job["progressive"], job["method"], job["options"],
            job["denoise"]) == ("sobol", -5, False, "path-mis", {"heuristic": "balance"}, True), job


def test04_watch_shows_progress_and_exits_0_when_done(server, client, tmp_path):
    log = tmp_path / "watch.err"
    with blocker(client), open(log, "w") as err:
        job = blocked_job(client)
        watch = subprocess.Popen([*rayfarm_command(), "watch", job["id"], "--server", server],
                                 stdout=subprocess.PIPE, stderr=err, text=True)
        wait_for(lambda: "running" in log.read_text() or watch.poll() is not None, 60,
                 "watch to draw its bar")
    # Leaving the blocker canceled it: the job runs now.
    try:
        stdout, _ = watch.communicate(timeout=120)
    finally:
        watch.kill()
    stderr = log.read_text()
    assert watch.returncode == 0 and stdout == "", stderr
    frames = stderr.replace("\r", "\n").splitlines()
    running = [i for i, f in enumerate(frames) if f"{job['id']} running    0%" in f]
    done = [i for i, f in enumerate(frames) if f"{job['id']} done     100%" in f]
    assert running and done and running[0] < done[0], frames
    final = frames[done[-1]]
    units = planned_units(TINY)  # 3 passes, a unit each
    assert "4.1k/4.1k samples" in final and f"units {units}/{units}" in final, final
    assert "samples/s" in final and "ETA 0.0s" in final, final
    assert f"job {job['id']} done" in stderr and "Traceback" not in stderr


def test05_fetch_writes_the_exr_bit_identical_to_an_in_process_render(tiny_job, server, client,
                                                                      tmp_path,
                                                                      reference_channels):
    job_id, _ = tiny_job
    client.wait(job_id)
    out = cli("fetch", job_id, "-o", str(tmp_path / "sub" / "tiny.exr"), server=server)
    assert out.returncode == 0 and out.stdout == "", out.stderr
    assert_bit_identical(channels_of(tmp_path / "sub" / "tiny.exr"), reference_channels(TINY))
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "sub" / "tiny.exr").stat().st_mode & 0o777 == 0o666 & ~umask  # not private
    out = cli("fetch", job_id, "--png", server=server, cwd=tmp_path)  # default name: ID.png
    assert out.returncode == 0, out.stderr
    from PIL import Image

    assert Image.open(tmp_path / f"{job_id}.png").size == (32, 32)
    assert sorted(p.name for p in tmp_path.rglob("*")) == sorted(["sub", "tiny.exr",
                                                                  f"{job_id}.png"])


def test06_jobs_lists_the_job_as_a_table(tiny_job, server, client):
    job_id, _ = tiny_job
    client.wait(job_id)
    out = cli("jobs", "--status", "done", "--limit", "50", server=server)
    assert out.returncode == 0, out.stderr
    header, *rows = out.stdout.splitlines()
    assert header.split() == ["ID", "STATUS", "SCENE", "METHOD", "SAMPLER", "SPP", "PROGRESS",
                              "ELAPSED", "ETA"]
    row = next(r.split() for r in rows if r.startswith(job_id))
    assert row[:7] == [job_id, "done", "cornell-box", "path-mis", "sobol", "4", "100%"], row
    assert row[8] == "0.0s" and row[7].endswith("s"), row
    listed = json.loads(cli("jobs", "--json", "--limit", "1", server=server).stdout)
    assert len(listed) == 1 and listed[0]["id"] == client.jobs(limit=1)[0]["id"]
    # filters: the alias finds its method's jobs; none of another method's
    path = json.loads(cli("jobs", "--json", "--method", "path", "--sampler", "sobol",
                          "--limit", "500", server=server).stdout)
    assert job_id in {j["id"] for j in path}
    none = cli("jobs", "--method", "raster", "--scene", "no-such-scene", server=server)
    assert none.returncode == 0 and "no jobs with method raster, scene no-such-scene" in none.stderr
    assert_clean_failure(cli("jobs", "--method", "nope", server=server), 2, "unknown method")


def test07_an_invalid_field_exits_2_naming_it(server):
    assert_clean_failure(cli("submit", *TINY_ARGS, "--spp", "0", server=server), 2,
                         "spp: must be between 1 and")
    assert_clean_failure(cli("submit", *TINY_ARGS, "--priority", "101", server=server), 2,
                         "priority: ")
    assert_clean_failure(cli("submit", "no-such-scene", server=server), 2,
                         "scene: unknown scene 'no-such-scene'")
    assert_clean_failure(cli("submit", *TINY_ARGS, "--option", "heuristic=nope", server=server),
                         2, "options.heuristic: must be one of")
    assert_clean_failure(cli("submit", *TINY_ARGS, "--option", "heuristic", server=server), 2,
                         "option: expects KEY=VALUE")
    assert_clean_failure(cli("submit", "missing/scene.json", server=server), 2,
                         "scene: no such scene file: missing/scene.json")
    assert_clean_failure(cli("jobs", "--status", "finished", server=server), 2,
                         "status: unknown status 'finished'")


def test08_an_unknown_job_is_a_clear_message(server):
    for command in (["watch"], ["fetch"], ["fetch", "--png"], ["cancel"]):
        out = cli(*command, "0123456789ab", server=server)
        assert_clean_failure(out, 1, "no job '0123456789ab'")


def test09_an_unreachable_server_is_a_clear_message():
    dead = f"127.0.0.1:{free_port()}"
    for command in (["jobs"], ["submit", "cornell-box"], ["watch", "0123456789ab"],
                    ["fetch", "0123456789ab"], ["workers"]):
        assert_clean_failure(cli(*command, server=dead), 3,
                             f"cannot reach the rayfarm service at http://{dead}",
                             "Connection refused", "RAYFARM_SERVER")
    # Without --server: $RAYFARM_SERVER names it.
    assert_clean_failure(cli("jobs", server=None, env={"RAYFARM_SERVER": f"http://{dead}"}), 3,
                         f"at http://{dead}")


def test10_cancel_ends_a_watch_with_exit_1(server, client):
    with blocker(client):
        job = blocked_job(client)
        watch = subprocess.Popen([*rayfarm_command(), "watch", job["id"], "--quiet",
                                  "--server", server], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        try:
            out = cli("cancel", job["id"], server=server)
            assert out.returncode == 0 and out.stdout == f"{job['id']} canceled\n", out.stderr
            _, stderr = watch.communicate(timeout=60)
        finally:
            watch.kill()
    assert watch.returncode == 1, stderr
    assert f"job {job['id']} canceled: canceled by request" in stderr and "Traceback" not in stderr
    again = cli("cancel", job["id"], server=server)
    assert_clean_failure(again, 1, "cannot go from 'canceled' to 'canceled'")


def test11_workers_lists_the_local_pool(server):
    out = cli("workers", server=server)
    assert out.returncode == 0, out.stderr
    header, *rows = out.stdout.splitlines()
    assert header.split()[:4] == ["NAME", "KIND", "STATE", "PROCS"] and len(rows) == 1
    assert rows[0].split()[1:2] == ["local"] and rows[0].split()[3] == "2", rows


# -- the Python client ------------------------------------------------------------------------

def test12_events_yield_job_units_unit_preview_end_in_order(client):
    with blocker(client) as big:
        job = blocked_job(client)
        stream = client.events(job["id"])
        first = [next(stream), next(stream)]
        client.cancel(big["id"])
        rest = list(stream)
    (kind0, snapshot), (kind1, units) = first
    assert (kind0, snapshot["id"], snapshot["status"]) == ("job", job["id"], "running")
    assert kind1 == "units" and [u["index"] for u in units] == list(range(planned_units(TINY)))
    assert {u["state"] for u in units} == {"pending"}
    kinds = [kind for kind, _ in rest]
    assert kinds[-1] == "end" and kinds.count("end") == 1
    assert rest[-1][1] == {"job_id": job["id"], "status": "done"}
    assert rest[-2][0] == "job" and rest[-2][1]["status"] == "done"
    first_unit, first_preview = kinds.index("unit"), kinds.index("preview")
    last_preview = len(kinds) - 1 - kinds[::-1].index("preview")
    assert first_unit < first_preview and last_preview < len(kinds) - 2, kinds
    unit_events = [data for kind, data in rest if kind == "unit"]
    assert {u["job_id"] for u in unit_events} == {job["id"]}
    assert {u["index"] for u in unit_events if u["state"] == "done"} == set(range(len(units)))
    final_preview = [data for kind, data in rest if kind == "preview"][-1]
    assert final_preview["units"] == len(units)
    assert httpx.get(client.base_url + final_preview["url"], headers=ADMIN_HEADERS).headers["content-type"] == "image/png"


def test13_events_reconnect_once_after_a_dropped_connection(server, client):
    flaky, gone = CuttableProxy(server), CuttableProxy(server)
    try:
        with RayfarmClient(flaky.url) as via_flaky, RayfarmClient(gone.url) as via_gone:
            with blocker(client) as big:
                job = blocked_job(client)
                stream = via_flaky.events(job["id"])
                assert [kind for kind, _ in (next(stream), next(stream))] == ["job", "units"]
                lost = via_gone.events(big["id"])
                assert next(lost)[0] == "job"
                gone.close()  # drops the stream and refuses the reconnection
                flaky.cut()  # drops the stream; the reconnection gets through
                client.cancel(big["id"])
                with pytest.raises(ServerUnavailable, match="lost the event stream of job "
                                                            f"{big['id']}"):
                    for _ in lost:
                        pass
                t0 = time.monotonic()
                rest = list(stream)
                waited = time.monotonic() - t0
    finally:
        flaky.close()
        gone.close()
    kinds = [kind for kind, _ in rest]
    # After the service's `retry: 2000` ms, a fresh snapshot, then on to the end.
    assert kinds[:2] == ["job", "units"] and kinds[-1] == "end", kinds
    assert rest[-1][1]["status"] == "done" and waited >= 1.9


def test14_client_errors_carry_what_a_person_needs(tiny_job, client, tmp_path):
    with pytest.raises(Invalid) as invalid:
        client.submit(**dict(TINY, spp=0))
    assert invalid.value.field == "spp" and invalid.value.status_code == 422
    assert invalid.value.message.startswith("must be between 1 and")
    assert str(invalid.value) == f"spp: {invalid.value.message}"
    with pytest.raises(Invalid) as invalid:
        client.submit(**dict(TINY, priority=500, depth=-1))
    assert {field for field, _ in invalid.value.errors} >= {"priority"}
    with pytest.raises(NotFound, match="no job '0123456789ab'"):
        client.job("0123456789ab")
    job_id, _ = tiny_job
    assert client.wait(job_id)["status"] == "done"
    with pytest.raises(Conflict, match="cannot go from 'done' to 'canceled'"):
        client.cancel(job_id)
    with RayfarmClient(f"127.0.0.1:{free_port()}") as dead:
        with pytest.raises(ServerUnavailable, match="cannot reach the rayfarm service"):
            dead.jobs()
        with pytest.raises(ServerUnavailable, match="cannot reach"):
            next(dead.events(job_id))


def test15_an_unfinished_result_is_not_found_and_nothing_is_written(client, tmp_path):
    with blocker(client):
        job = blocked_job(client)
        with pytest.raises(NotFound, match="is running; its result.exr exists once it is done"):
            client.download_result(job["id"], tmp_path / "early.exr")
        assert list(tmp_path.iterdir()) == []
        out = cli("fetch", job["id"], "-o", str(tmp_path / "early.exr"), server=client.base_url)
        assert_clean_failure(out, 1, "is running", "--wait")
        assert list(tmp_path.iterdir()) == []
        # --wait waits for the job (the blocker is canceled right after it starts waiting).
        fetch = subprocess.Popen([*rayfarm_command(), "fetch", job["id"], "--wait", "-o",
                                  str(tmp_path / "late.exr"), "--server", client.base_url],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _, stderr = fetch.communicate(timeout=120)
    finally:
        fetch.kill()
    assert fetch.returncode == 0, stderr
    assert [p.name for p in tmp_path.iterdir()] == ["late.exr"]


# -- scene files ---------------------------------------------------------------------------------

def cornell_file(directory: Path, *, mesh: bool) -> Path:
    """cornell-box as a scene file; with `mesh`, its small box is `box.obj` beside it."""
    doc = json.loads((ROOT / "renderer" / "scenes" / "cornell-box.json").read_text())
    doc["name"] = "cornell-file"
    if mesh:
        small = next(s for s in doc["shapes"] if s["name"] == "small-box")
        small.update(type="mesh", file="box.obj")
        corners = [(x, y, z) for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]
        faces = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3),
                 (2, 4, 8, 6)]
        (directory / "box.obj").write_text(
            "".join(f"v {x} {y} {z}\n" for x, y, z in corners)
            + "".join("f " + " ".join(map(str, f)) + "\n" for f in faces))
    path = directory / "scene.json"
    path.write_text(json.dumps(doc))
    return path


def scene_file_body(path: Path) -> dict:
    from renderer import resolve_document

    return dict(TINY, scene=resolve_document(path))  # meshes read and inlined


def takes_uploads(farm: RayfarmClient) -> bool:
    paths = httpx.get(f"{farm.base_url}/openapi.json", timeout=30, headers=ADMIN_HEADERS).json()["paths"]
    return "post" in paths.get("/scenes", {})


def test16_submit_of_a_mesh_less_scene_file_renders_it(server, client, tmp_path,
                                                        reference_channels):
    path = cornell_file(tmp_path, mesh=False)
    args = [a if a != "cornell-box" else str(path) for a in TINY_ARGS]
    out = cli("submit", *args, server=server)
    assert out.returncode == 0, out.stderr
    job_id = out.stdout.strip()
    # Uploaded where the service takes uploads; sent inline where it does not.
    assert ("uploaded scene.json" if takes_uploads(client) else "sending scene.json inline") \
        in out.stderr
    assert client.wait(job_id)["status"] == "done"
    client.download_result(job_id, tmp_path / "file.exr")
    assert_bit_identical(channels_of(tmp_path / "file.exr"),
                         reference_channels(scene_file_body(path)))


def test17_submit_uploads_a_scene_file_with_its_meshes(server, client, tmp_path,
                                                       reference_channels):
    if not takes_uploads(client):
        pytest.skip("this checkout's service has no POST /scenes (the scenes-upload branch "
                    "adds it); upload_scene follows its contract and is tested once merged")
    path = cornell_file(tmp_path, mesh=True)
    record = client.upload_scene(path)
    assert record["id"] and client.upload_scene(path)["id"] == record["id"]  # stored once
    args = [a if a != "cornell-box" else str(path) for a in TINY_ARGS]
    out = cli("submit", *args, server=server)
    assert out.returncode == 0, out.stderr
    assert f"uploaded scene.json as scene {record['id']}" in out.stderr
    job_id = out.stdout.strip()
    # The same scene with its mesh in a subfolder, sent as a file with its
    # relative path, as a folder and as a zip (`rayfarm upload`): one scene.
    folder = tmp_path / "folder"
    (folder / "models").mkdir(parents=True)
    doc = json.loads(path.read_text())
    next(s for s in doc["shapes"] if s.get("file"))["file"] = "models/box.obj"
    (folder / "scene.json").write_text(json.dumps(doc))
    (folder / "models" / "box.obj").write_bytes((tmp_path / "box.obj").read_bytes())
    assert client.upload_scene(folder / "scene.json")["id"] == record["id"]
    archive = shutil.make_archive(str(tmp_path / "packed"), "zip", folder)
    for sent in (folder, archive):
        out = cli("upload", str(sent), server=server)
        assert out.returncode == 0 and out.stdout.strip() == record["id"], out.stderr
        assert f"uploaded {Path(sent).name} as scene {record['id']}" in out.stderr
    shown = cli("scenes", record["id"], server=server).stdout
    assert "source: scene.json" in shown and "every element as written" in shown, shown
    assert_clean_failure(cli("upload", str(tmp_path / "nothing"), server=server), 2,
                         "no such file or folder")
    assert client.wait(job_id)["status"] == "done"
    client.download_result(job_id, tmp_path / "mesh.exr")
    assert_bit_identical(channels_of(tmp_path / "mesh.exr"),
                         reference_channels(scene_file_body(path)))


def test17b_a_mitsuba_file_its_folder_and_the_folder_zipped_upload_as_one_scene(client,
                                                                               tmp_path):
    """`rayfarm upload` of veach-bidir's scene.xml and of its folder, and the
    folder zipped as `zip -r` packs it: one scene, named after its folder as
    the importer names it locally (the file's folder, not the service's)."""
    from renderer import scene_text
    from renderer.cli import load_scene as read_scene_file  # what `rayfarm render FILE` reads

    folder = real_scenes("veach-bidir/scene.xml") / "veach-bidir"
    local = read_scene_file(str(folder / "scene.xml"))
    records = [client.upload_scene(sent) for sent in
               (folder / "scene.xml", folder, zip_of_folder(folder, tmp_path))]
    assert {r["id"] for r in records} == {scene_text(local)[0]}, records
    assert {r["name"] for r in records} == {local["name"]} == {"veach-bidir"}


def test18_a_scene_file_with_a_missing_mesh_is_refused_before_sending(server, tmp_path):
    path = cornell_file(tmp_path, mesh=True)
    (tmp_path / "box.obj").unlink()
    args = [a if a != "cornell-box" else str(path) for a in TINY_ARGS]
    assert_clean_failure(cli("submit", *args, server=server), 2,
                         "scene.shapes[6].file: file not found")


def test19_client_commands_load_neither_the_renderer_nor_the_server(server):
    probe = ("import sys\nfrom service.cli import main\n"
             f"assert main(['jobs', '--server', {server!r}]) == 0\n"
             "heavy = {'renderer', 'worker', 'numba', 'numpy', 'fastapi', 'sqlalchemy', 'celery',"
             " 'uvicorn'}\n"
             "print(sorted({m.split('.')[0] for m in sys.modules} & heavy))\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "[]", out.stdout


def test20_the_token_comes_from_the_flag_the_environment_or_a_token_file(server, tmp_path):
    from service.client import Unauthorized

    # No token anywhere (and no ./rayfarm-data/admin.token in that directory): 401, said clearly.
    out = cli("jobs", server=server, env={"RAYFARM_TOKEN": ""}, cwd=tmp_path)
    assert_clean_failure(out, 1, "token", "RAYFARM_TOKEN")
    bad = cli("jobs", "--token", "rf_wrong", server=server, cwd=tmp_path)
    assert_clean_failure(bad, 1, "invalid, expired or revoked token")
    token_file = tmp_path / "token"
    token_file.write_text(TEST_ADMIN_TOKEN + "\n")
    by_file = cli("jobs", server=server, cwd=tmp_path,
                  env={"RAYFARM_TOKEN": "", "RAYFARM_TOKEN_FILE": str(token_file)})
    assert by_file.returncode == 0, by_file.stderr
    data = tmp_path / "rayfarm-data"
    data.mkdir()
    (data / "admin.token").write_text(TEST_ADMIN_TOKEN)
    assert cli("jobs", server=server, cwd=tmp_path, env={"RAYFARM_TOKEN": ""}).returncode == 0
    with RayfarmClient(server, token="rf_wrong") as farm:
        with pytest.raises(Unauthorized):
            farm.jobs()


def test21_submit_to_a_noise_target_watches_the_error_fall(server, client):
    """`rayfarm submit --target REL --spp CEILING --watch`: the job stops at its
    target, the bar and the last line speak in error (service/targets.py)."""
    out = cli("submit", "cornell-box", "--method", "path-mis", "--depth", "5", "--width", "32",
              "--height", "32", "--tile-size", "8", "--seed", "3", "--spp", "1024",
              "--target", "0.25", "--watch", server=server, timeout=300)
    assert out.returncode == 0, out.stderr
    job = client.job(out.stdout.strip())
    assert job["status"] == "done" and job["target_stop"] == "target"
    assert job["target"] == {"rel_error": 0.25, "max_spp": 1024, "max_seconds": None}
    assert "to 25 % error, at most 1024 spp" in out.stderr, out.stderr
    frames = out.stderr.replace("\r", "\n")
    assert "-> 25 %" in frames and "units skipped" in frames, frames
    assert "(target 25 %, stopped by target)" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr


def test22_the_job_actions_priority_scenes_and_methods_from_the_cli(server, client):
    """pause, resume, priority, cancel, retry, requeue and delete act on the
    job and print its new status; a job not in a state for the action, or
    gone, is said on stderr with exit 1; scenes and methods list the registries."""
    job = client.submit(scene="cornell-box", method="path", spp=4096, depth=5, width=64,
                        height=64, tile_size=16, progressive=False)  # long enough to act on
    job_id = job["id"]

    def ok(*args: str) -> str:
        out = cli(*args, server=server)
        assert out.returncode == 0, (args, out.stderr)
        return out.stdout.strip()

    assert ok("pause", job_id) == f"{job_id} paused"
    assert ok("priority", job_id, "7") == f"{job_id} priority 7"
    assert client.job(job_id)["priority"] == 7
    assert ok("resume", job_id) in (f"{job_id} running", f"{job_id} queued")
    assert ok("cancel", job_id) == f"{job_id} canceled"
    assert_clean_failure(cli("retry", job_id, server=server), 1, "no failed units")
    assert ok("requeue", job_id) == f"{job_id} queued"
    assert ok("cancel", job_id) == f"{job_id} canceled"
    assert ok("delete", job_id) == f"{job_id} deleted"
    assert_clean_failure(cli("delete", job_id, server=server), 1, f"no job '{job_id}'")
    assert_clean_failure(cli("priority", job_id, "500", server=server), 2, "priority")
    scenes = ok("scenes")
    assert scenes.splitlines()[0].split() == ["ID", "KIND", "NAME", "SIZE", "TRIANGLES", "REPORT"]
    assert any(line.split()[:2] == ["cornell-box", "builtin"] for line in scenes.splitlines())
    assert ok("scenes", "cornell-box").splitlines()[:3] == [
        "id: cornell-box", "kind: builtin", "name: cornell-box"]
    methods = {line.split()[0]: line.split() for line in ok("methods").splitlines()[1:]}
    assert methods["path-mis"][1] == "path" and methods["path-mis"][4] == "yes"
    assert methods["photon"][4] == "no"
    assert {m["name"] for m in json.loads(ok("methods", "--json"))} == set(methods)


def test23_an_experiment_from_the_cli_waits_and_prints_its_table_csv_and_json(server, client):
    """rayfarm experiment submits an estimator-lab experiment (prints its id),
    --wait prints the report's table; --show ID with --csv or --json prints
    the same as the API; a bad experiment is exit 2 naming the field."""
    out = cli("experiment", "cornell-box", "--methods", "path-mis", "raster", "--spp", "2", "8",
              "--repeats", "3", "--width", "16", "--depth", "3", "--wait", "--quiet",
              server=server, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].split()[:5] == ["CONFIG", "SPP", "SIG.", "BLOCKS", "BIAS"]
    rows = {line.split()[0]: line.split() for line in lines[1:] if line[0] != " "}
    assert set(rows) == {"path-mis", "raster"}
    assert rows["raster"][-2:] == ["no", "no"] and rows["path-mis"][-2:] == ["yes", "yes"]
    experiment_id = out.stderr.split(":")[1].strip().split()[0]
    experiment = client.experiment(experiment_id)
    assert experiment["status"] == "done"
    csv_out = cli("experiment", "--show", experiment_id, "--csv", server=server)
    assert csv_out.returncode == 0 and csv_out.stdout == client.experiment_csv(experiment_id)
    shown = json.loads(cli("experiment", "--show", experiment_id, "--json", server=server).stdout)
    assert shown["report"] == experiment["report"]
    listed = cli("experiment", "--list", server=server).stdout
    assert experiment_id in listed
    assert_clean_failure(cli("experiment", "cornell-box", "--methods", "path-mis", "--spp", "8", "2",
                             server=server), 2, "spp")
