"""Bytes a DAG job moves over Redis: a photon-mapping job on the Celery farm.

    python bench/artefacts.py                          # measure this checkout
    python bench/artefacts.py --save before.json       # keep the figure
    python bench/artefacts.py --compare before.json    # print both side by side

It starts its own `redis-server` on a free port (no persistence), one
`rayfarm worker` process and the service in this process (Celery executor,
a temporary data dir), renders one warm-up job (kernels load, the scene
reaches the worker), then reads Redis's own counters (`INFO stats`:
total_net_input_bytes, what clients sent; total_net_output_bytes, what they
received) before and after one SPPM job of several photon rounds:
`--iterations` rounds (iterations_per_unit=1), each a photon unit (a photon
array, ~40 bytes a photon) that every gather tile of the round reads, and one
gather unit per tile that also reads the same tile's previous round.

Everything on that Redis is counted: unit results and artefacts, task
messages, result metadata the service polls, heartbeats and worker presence.
The last three grow with time, not data, so the bench also prints the job's
wall time.

To measure the code before artefacts travelled by digest, export that
commit's service and worker (the renderer did not change, so its compiled
kernels are reused) and put them first on the path:

    git archive d190b6c service worker | tar -x -C /tmp/base-svc
    cd /tmp/base-svc && PYTHONPATH=/tmp/base-svc:$REPO python $REPO/bench/artefacts.py \
        --label before --save /tmp/before.json
    cd $REPO && python bench/artefacts.py --label after --compare /tmp/before.json

Recorded on the defaults (2 cores shared with other work, so the seconds are noise):

                              before (d190b6c)   after (digests)
    Redis in (sent)               41.49 MB          12.41 MB
    Redis out (received)          42.69 MB          39.66 MB
    Redis in + out                84.18 MB          52.07 MB   (x 0.62)

What went: every film base64'd into the result backend (x 4/3) and read
back, and every input uploaded again by the service. What stays: each film
sent once by its worker and read once by the service, and the gather units'
reads of their inputs (the "out" column; a worker process keeps its last 4).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.05)


def net_bytes(client) -> tuple[int, int]:
    stats = client.info("stats")
    return int(stats["total_net_input_bytes"]), int(stats["total_net_output_bytes"])


def run_job(client, body: dict, timeout: float = 600.0) -> dict:
    response = client.post("/jobs", json=body)
    assert response.status_code == 201, response.text
    job_id = response.json()["id"]

    def final():
        job = client.get(f"/jobs/{job_id}").json()
        return job if job["status"] in ("done", "failed", "canceled") else None
    job = wait_for(final, timeout, f"job {job_id}")
    if job["status"] != "done":
        raise SystemExit(f"job {job_id} {job['status']}: {job.get('error')}")
    return job


def measure(args: argparse.Namespace) -> dict:
    import redis
    from fastapi.testclient import TestClient

    from service.main import create_app
    from service.settings import Settings

    workdir = Path(tempfile.mkdtemp(prefix="rayfarm-bench-artefacts-"))
    token = "rf_bench-" + secrets.token_urlsafe(32)
    port = free_port()
    server = subprocess.Popen([shutil.which("redis-server") or "redis-server", "--port", str(port),
                               "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                               "--dir", str(workdir)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)
    url = f"redis://127.0.0.1:{port}/0"
    broker = redis.Redis.from_url(url)
    worker = None
    try:
        wait_for(lambda: _pings(broker), 30, "redis-server")
        env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
        env.update(RAYFARM_BROKER_URL=url, PYTHONUNBUFFERED="1",
                   RAYFARM_CACHE_DIR=str(workdir / "cache"))
        log_path = workdir / "worker.log"
        with open(log_path, "wb") as log:
            worker = subprocess.Popen([sys.executable, "-m", "service", "worker",
                                       "--concurrency", str(args.workers), "--loglevel", "info"],
                                      env=env, stdout=log, stderr=subprocess.STDOUT,
                                      start_new_session=True)
        wait_for(lambda: " ready." in log_path.read_text(errors="replace")
                 or worker.poll() is not None, 300, "the worker")
        if worker.poll() is not None:
            raise SystemExit(f"worker exited:\n{log_path.read_text(errors='replace')}")
        settings = Settings(data_dir=workdir / "data", broker_url=url, poll_interval=0.05,
                            admin_token=token)
        body = {"scene": "cornell-box", "method": "photon", "spp": args.iterations,
                "depth": 5, "width": args.size, "height": args.size, "tile_size": args.tile,
                "seed": 3, "progressive": False,
                "options": {"iterations_per_unit": 1, "photons": args.photons}}
        with TestClient(create_app(settings),
                        headers={"Authorization": f"Bearer {token}"}) as client:
            run_job(client, dict(body, spp=1, width=16, height=16, tile_size=16))  # warm-up
            before_in, before_out = net_bytes(broker)
            started = time.perf_counter()
            job = run_job(client, body)
            seconds = time.perf_counter() - started
            after_in, after_out = net_bytes(broker)
        return {"commit": args.label, "units": job["progress"]["units_total"],
                "seconds": round(seconds, 2), "redis_in": after_in - before_in,
                "redis_out": after_out - before_out,
                "redis_total": after_in - before_in + after_out - before_out}
    finally:
        if worker is not None and worker.poll() is None:
            os.killpg(worker.pid, signal.SIGTERM)
            try:
                worker.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(worker.pid, signal.SIGKILL)
        broker.close()
        server.terminate()
        server.wait(10)
        shutil.rmtree(workdir, ignore_errors=True)


def _pings(client) -> bool:
    import redis

    try:
        return client.ping()
    except redis.RedisError:
        return False


def _mb(n: int) -> str:
    return f"{n / 1e6:10.2f} MB"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=64, help="image width and height")
    parser.add_argument("--tile", type=int, default=16, help="gather tile size")
    parser.add_argument("--iterations", type=int, default=8, help="SPPM rounds (spp)")
    parser.add_argument("--photons", type=int, default=16384, help="photons a round")
    parser.add_argument("--workers", type=int, default=2, help="render processes")
    parser.add_argument("--label", default="this checkout", help="name of the measured code")
    parser.add_argument("--save", type=Path, help="write the figures to this JSON file")
    parser.add_argument("--compare", type=Path, help="JSON of an earlier run to show beside")
    args = parser.parse_args()
    figures = measure(args)
    if args.save:
        args.save.write_text(json.dumps(figures, indent=1))
    runs = [json.loads(args.compare.read_text()), figures] if args.compare else [figures]
    print(f"photon job: {args.size}x{args.size}, {args.iterations} rounds of {args.photons} "
          f"photons, {args.tile}x{args.tile} gather tiles, {args.workers} render processes")
    print(f"{'':18}" + "".join(f"{r['commit'][:22]:>24}" for r in runs))
    for key, label in (("units", "units"), ("seconds", "job seconds"),
                       ("redis_in", "Redis in (sent)"), ("redis_out", "Redis out (received)"),
                       ("redis_total", "Redis in + out")):
        cells = [f"{r[key]:>24}" if key in ("units", "seconds") else f"{_mb(r[key]):>24}"
                 for r in runs]
        print(f"{label:18}" + "".join(cells))
    if len(runs) == 2 and runs[0]["redis_total"]:
        print(f"{'after / before':18}{runs[1]['redis_total'] / runs[0]['redis_total']:>48.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
