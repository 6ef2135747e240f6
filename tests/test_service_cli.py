"""The `rayfarm` command: subcommands, forwarding to the renderer's CLI."""

from __future__ import annotations

import json
import re
import subprocess

import pytest

from renderer import read_exr
from renderer.metadata import METADATA_KEYS
from service.cli import main

from conftest import ADMIN_HEADERS, assert_denoised_beside_raw, channels_of, rayfarm_command


def test01_console_script_lists_the_subcommands():
    out = subprocess.run([*rayfarm_command(), "--help"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0
    for sub in ("serve", "worker", "render", "submit", "watch", "fetch", "jobs", "cancel",
                "workers"):
        assert sub in out.stdout


def test02_render_forwards_argv_to_the_renderer_cli(capsys):
    with pytest.raises(SystemExit) as info:
        main(["render", "--help"])
    assert info.value.code == 0
    assert "usage: rayfarm render" in capsys.readouterr().out


def test03_render_runs_a_tiny_job(tmp_path):
    out = tmp_path / "tiny.exr"
    code = main(["render", "cornell-box", "--spp", "2", "--depth", "2", "--width", "8",
                 "--height", "8", "--tile-size", "8", "--workers", "1", "--quiet",
                 "--out", str(out)])
    assert code == 0 and out.is_file()
    # --denoise: the same raw channels, and denoised.R/G/B and a denoised PNG beside them
    denoised = tmp_path / "denoised.exr"
    code = main(["render", "cornell-box", "--spp", "2", "--depth", "2", "--width", "8",
                 "--height", "8", "--tile-size", "8", "--workers", "1", "--quiet", "--denoise",
                 "--out", str(denoised)])
    assert code == 0 and denoised.with_suffix(".denoised.png").is_file()
    assert_denoised_beside_raw(denoised, channels_of(out))
    # --target: passes until the error statistic meets it (renderer/target.py)
    targeted = tmp_path / "targeted.exr"
    code = main(["render", "cornell-box", "--spp", "64", "--depth", "2", "--width", "16",
                 "--height", "16", "--tile-size", "8", "--workers", "1", "--quiet",
                 "--target", "0.5", "--out", str(targeted)])
    _, header = read_exr(targeted)
    assert code == 0 and header["rayfarm.rel_error"] <= 0.5
    assert json.loads(header["rayfarm.target"]) == {"rel_error": 0.5, "max_spp": 64,
                                                    "max_seconds": None}
    code = main(["render", "cornell-box", "--method", "bdpt", "--target", "0.5",
                 "--out", str(tmp_path / "refused.exr")])
    assert code == 2


def test03b_render_types_method_options_and_names_a_bad_one(tmp_path, capsys):
    """`--option` values arrive as text: numbers are typed by the method's option
    table (MLT's bounded `chains`, `large_step`), and a bad one is named."""
    out = tmp_path / "mlt.exr"
    code = main(["render", "cornell-box", "--method", "mlt", "--spp", "2", "--depth", "2",
                 "--width", "8", "--height", "8", "--workers", "1", "--quiet",
                 "--option", "chains=16", "--option", "large_step=0.5", "--out", str(out)])
    assert code == 0 and out.is_file()
    code = main(["render", "cornell-box", "--method", "mlt", "--option", "chains=many",
                 "--out", str(tmp_path / "bad.exr")])
    assert code == 2 and "options.chains" in capsys.readouterr().err


def test04_worker_without_broker_refuses_with_a_hint(monkeypatch, capsys):
    monkeypatch.delenv("RAYFARM_BROKER_URL", raising=False)
    assert main(["worker"]) == 2
    assert "RAYFARM_BROKER_URL" in capsys.readouterr().err


def test05_serve_in_embedded_mode_renders_over_http(embedded_serve, tmp_path, reference_channels):
    import httpx

    from conftest import TINY, assert_bit_identical, channels_of, poll_job

    serve, base = embedded_serve
    with httpx.Client(base_url=base, timeout=30, headers=ADMIN_HEADERS) as client:
        assert client.get("/healthz").json()["executor"] == "local"
        job_id = client.post("/jobs", json=TINY).json()["id"]
        job = poll_job(lambda path: client.get(path).json(), job_id)
        assert job["status"] == "done", job
        (tmp_path / "out.exr").write_bytes(client.get(job["result_url"]).content)
    assert "Traceback" not in serve.log(), serve.log()
    assert_bit_identical(channels_of(tmp_path / "out.exr"), reference_channels(TINY))
    # `rayfarm render` of the same job writes the same pixels and the same
    # header keys with the same types (renderer.metadata)
    local = tmp_path / "local.exr"
    assert main(["render", TINY["scene"], "--method", TINY["method"], "--spp", str(TINY["spp"]),
                 "--depth", str(TINY["depth"]), "--tile-size", str(TINY["tile_size"]),
                 "--seed", str(TINY["seed"]), "--width", str(TINY["width"]),
                 "--height", str(TINY["height"]), "--workers", "1", "--quiet",
                 "--out", str(local)]) == 0
    assert_bit_identical(channels_of(local), channels_of(tmp_path / "out.exr"))
    _, farm_header = read_exr(tmp_path / "out.exr")
    _, local_header = read_exr(local)
    farm_keys = {k: type(v) for k, v in farm_header.items() if k.startswith("rayfarm.")}
    assert farm_keys == {k: type(v) for k, v in local_header.items() if k.startswith("rayfarm.")}
    assert set(farm_keys) == {f"rayfarm.{k}" for k in METADATA_KEYS}
    differ = {"rayfarm.job_id", "rayfarm.render_seconds"}  # the farm's job, timings
    assert {k: farm_header[k] for k in farm_keys if k not in differ} \
        == {k: local_header[k] for k in farm_keys if k not in differ}
    assert (farm_header["rayfarm.job_id"], local_header["rayfarm.job_id"]) == (job_id, "")
    assert farm_header["rayfarm.method"] == "path-mis" and farm_header["rayfarm.depth"] == 3
    assert farm_header["rayfarm.samples"] == str(32 * 32 * 4)
    for header in (farm_header, local_header):
        assert header["software"].startswith("rayfarm ") and header["utcOffset"] == 0.0
        assert re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", header["capDate"])
        assert isinstance(header["rayfarm.render_seconds"], float)


def test06_serve_prints_a_login_url_that_logs_a_browser_in(tmp_path):
    """A first start with no RAYFARM_ADMIN_TOKEN: `rayfarm serve` makes the admin,
    prints the login URL (Jupyter's way) and the URL's token works."""
    import re

    import httpx

    from conftest import embedded_env, start_serve

    # No admin token given: the service makes one and prints its login URL.
    env = embedded_env(tmp_path / "data", RAYFARM_LOCAL_WORKERS="1", RAYFARM_POLL_INTERVAL=None,
                       RAYFARM_ADMIN_TOKEN=None, RAYFARM_TOKEN=None)
    child, base = start_serve(env, tmp_path / "serve.log")
    try:
        url = re.search(r"http://127\.0\.0\.1:\d+/\?token=(rf_[\w-]+)", child.log())
        assert url, child.log()
        token = url.group(1)
        assert (tmp_path / "data" / "admin.token").read_text().strip() == token
        with httpx.Client(base_url=base, timeout=30) as browser:
            assert browser.get("/jobs").status_code == 401
            # opened from a terminal: the browser says `Sec-Fetch-Site: none`
            login = browser.get(f"/?token={token}", headers={"sec-fetch-site": "none"},
                                follow_redirects=False)
            assert login.status_code == 303 and login.headers["location"] == "/"
            assert browser.get("/auth/me").json()["user"] == "admin"  # by the cookie now
        assert "token=..." in child.log()  # the access log line of the login, redacted
        assert child.log().count(token) == 1  # in the printed URL only
    finally:
        child.stop()


def test07_serve_keeps_the_files_it_writes_to_its_own_user(tmp_path):
    """Under the everyday umask 022, `rayfarm serve` still writes the ledger
    (and SQLite's -wal and -shm), scenes, unit films and logs, results and
    previews for its own user alone (RAYFARM_UMASK, default 077): before, they
    were world-readable (0644), directories 0755. A data directory made
    looser beforehand loses those bits at start."""
    import os
    import stat

    import httpx

    from conftest import TINY, embedded_env, poll_job, start_serve

    data = tmp_path / "data"
    data.mkdir(mode=0o755)
    os.chmod(data, 0o755)
    env = embedded_env(data, RAYFARM_LOCAL_WORKERS="1")
    old_umask = os.umask(0o022)  # what the child inherits
    try:
        child, base = start_serve(env, tmp_path / "serve.log")
    finally:
        os.umask(old_umask)
    try:
        with httpx.Client(base_url=base, timeout=30, headers=ADMIN_HEADERS) as client:
            job = poll_job(lambda path: client.get(path).json(),
                           client.post("/jobs", json=TINY).json()["id"])
            assert job["status"] == "done", job
            assert client.get(job["preview_url"]).status_code == 200
            assert client.get(f"/jobs/{job['id']}/units/0/log").status_code == 200
            written = {path.relative_to(data).as_posix(): stat.S_IMODE(path.lstat().st_mode)
                       for path in [data, *data.rglob("*")]}
    finally:
        child.stop()
    assert {"rayfarm.sqlite3", "rayfarm.sqlite3-wal", "rayfarm.sqlite3-shm", "admin.token",
            f"jobs/{job['id']}/result.exr", f"jobs/{job['id']}/preview.png"} <= set(written)
    assert any(name.endswith(".film") for name in written)
    assert any("/logs/" in name for name in written)
    readable = {name: oct(mode) for name, mode in written.items() if mode & 0o077}
    assert readable == {}, readable
    assert written["."] == 0o700 and written["jobs"] == 0o700
