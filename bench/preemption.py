"""A small job's wait behind another artist's long units, with cancel and without.

    python bench/preemption.py                       # both executors, both modes
    python bench/preemption.py --executor local --mode cancel
    python bench/preemption.py --save after.json     # keep the figures

Artist "a" submits two one-unit jobs (64 x 64 pixels, 32,768 spp, not
progressive: cornell-box, path, the default depth 5), and once both render,
artist "b" submits a one-unit 16 x 16 job (`--small-spp`, 32,768 by
default). Then either
- `cancel`: 3 s later a's jobs are canceled (preemption off, so that cancel
  alone frees the processes), or
- `preempt`: nothing is canceled; fair share over the render processes
  (service/fairshare.py) has to make room for b;
and the bench reports, for b's job: `start`, seconds from its submission
until its unit began rendering (the ledger's started_at); `render`, its
unit's own render seconds; `done`, seconds from submission until the job was
done. The wait behind a's units is about `done - render`.

Two render processes either way: the embedded pool (`local_workers=2`), or
one `rayfarm worker --concurrency 2` on a `redis-server` this bench starts on
a free port. The service runs in this process (a TestClient) with a
temporary data dir.

To measure the code before running units could be stopped, export that
commit's service and worker (the renderer's kernels did not change: their
compiled cache is reused) and put them first on the path:

    git archive 77e9ea8 service worker | tar -x -C /tmp/base-svc
    PYTHONPATH=/tmp/base-svc:$PWD python bench/preemption.py --label before --save before.json

Figures and the machine they were taken on: docs/hardening.md.
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
from datetime import datetime
from pathlib import Path

BIG = {"scene": "cornell-box", "method": "path", "spp": 32768, "depth": 5, "width": 64, "height": 64,
       "progressive": False}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for(predicate, timeout: float, what: str, interval: float = 0.05):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


def _pings(client) -> bool:
    import redis

    try:
        return client.ping()
    except redis.RedisError:
        return False


class Redis:
    """A redis-server of this bench and one `rayfarm worker` on it."""

    def __init__(self, workers: int):
        import redis

        self.dir = Path(tempfile.mkdtemp(prefix="rayfarm-bench-preempt-redis-"))
        port = free_port()
        self.server = subprocess.Popen(
            [shutil.which("redis-server") or "redis-server", "--port", str(port), "--bind",
             "127.0.0.1", "--save", "", "--appendonly", "no", "--dir", str(self.dir)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        self.url = f"redis://127.0.0.1:{port}/0"
        self.client = redis.Redis.from_url(self.url)
        wait_for(lambda: _pings(self.client), 30, "redis-server")
        env = {k: v for k, v in os.environ.items() if not k.startswith("RAYFARM_")}
        env.update(RAYFARM_BROKER_URL=self.url, PYTHONUNBUFFERED="1",
                   RAYFARM_CACHE_DIR=str(self.dir / "cache"))
        self.log_path = self.dir / "worker.log"
        with open(self.log_path, "wb") as log:
            self.worker = subprocess.Popen(
                [sys.executable, "-m", "service", "worker", "--concurrency", str(workers),
                 "--loglevel", "info"], env=env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True)
        wait_for(lambda: " ready." in self.log_path.read_text(errors="replace")
                 or self.worker.poll() is not None, 300, "the worker")
        if self.worker.poll() is not None:
            raise SystemExit(f"worker exited:\n{self.log_path.read_text(errors='replace')}")

    def close(self) -> None:
        if self.worker.poll() is None:
            os.killpg(self.worker.pid, signal.SIGTERM)
            try:
                self.worker.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(self.worker.pid, signal.SIGKILL)
        self.client.close()
        self.server.terminate()
        self.server.wait(10)
        shutil.rmtree(self.dir, ignore_errors=True)


def _seconds(later: str | None, earlier: str) -> float | None:
    if later is None:
        return None
    return (datetime.fromisoformat(later) - datetime.fromisoformat(earlier)).total_seconds()


def run(executor: str, mode: str, args: argparse.Namespace) -> dict:
    from fastapi.testclient import TestClient

    from service import auth
    from service.main import create_app
    from service.models import utcnow
    from service.settings import Settings

    workdir = Path(tempfile.mkdtemp(prefix="rayfarm-bench-preempt-"))
    token = "rf_bench-" + secrets.token_urlsafe(32)
    farm = Redis(args.workers) if executor == "celery" else None
    try:
        # Older code ignores `preemption` (it had none).
        settings = Settings(data_dir=workdir / "data", broker_url=farm.url if farm else "",
                            database_url="", local_workers=args.workers, poll_interval=0.2,
                            admin_token=token, preemption=mode == "preempt")
        with TestClient(create_app(settings),
                        headers={"Authorization": f"Bearer {token}"}) as admin:
            tokens = {}
            with admin.app.state.farm.sessions.begin() as session:
                for name in ("a", "b"):
                    auth.add_user(session, name, "artist", utcnow())
                    tokens[name] = auth.create_token(session, name, utcnow())[1]

            def post(owner: str, body: dict) -> str:
                response = admin.post("/jobs", json=body,
                                      headers={"Authorization": f"Bearer {tokens[owner]}"})
                assert response.status_code == 201, response.text
                return response.json()["id"]

            def rendering(job_id: str) -> bool:
                return any(u["state"] == "running"
                           for u in admin.get(f"/jobs/{job_id}/units").json())

            big = [post("a", BIG) for _ in range(2)]
            wait_for(lambda: all(rendering(j) for j in big), 600, "a's units to render")
            small = post("b", dict(BIG, width=16, height=16, spp=args.small_spp))
            if mode == "cancel":
                time.sleep(3.0)
                for job_id in big:
                    assert admin.post(f"/jobs/{job_id}/cancel").status_code == 200

            def finished():
                job = admin.get(f"/jobs/{small}").json()
                return job if job["status"] in ("done", "failed", "canceled") else None
            job = wait_for(finished, 3600, "b's job", interval=0.1)
            [unit] = admin.get(f"/jobs/{small}/units").json()
            big_status = [admin.get(f"/jobs/{j}").json()["status"] for j in big]
            for job_id in big:  # the next run starts afresh
                admin.post(f"/jobs/{job_id}/cancel")
        return {"executor": executor, "mode": mode, "status": job["status"],
                "start": _seconds(unit["started_at"], job["created"]),
                "render": unit["seconds"], "done": _seconds(job["finished"], job["created"]),
                "a_jobs_when_b_done": big_status, "small_spp": args.small_spp}
    finally:
        if farm is not None:
            farm.close()
        shutil.rmtree(workdir, ignore_errors=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--executor", choices=("local", "celery", "both"), default="both")
    parser.add_argument("--mode", choices=("cancel", "preempt", "both"), default="both")
    parser.add_argument("--small-spp", type=int, default=32768, help="b's job's spp")
    parser.add_argument("--workers", type=int, default=2, help="render processes")
    parser.add_argument("--label", default="this checkout", help="name of the measured code")
    parser.add_argument("--save", type=Path, help="write the figures to this JSON file")
    args = parser.parse_args()
    executors = ("local", "celery") if args.executor == "both" else (args.executor,)
    modes = ("cancel", "preempt") if args.mode == "both" else (args.mode,)
    figures = []
    for executor in executors:
        for mode in modes:
            result = run(executor, mode, args)
            result["label"] = args.label
            figures.append(result)
            print(f"{args.label}: {executor:6} {mode:7} b's job {result['status']}: "
                  f"started after {result['start']:.1f} s, rendered {result['render']:.1f} s, "
                  f"done after {result['done']:.1f} s (a's jobs then: "
                  f"{', '.join(result['a_jobs_when_b_done'])})", flush=True)
    if args.save:
        args.save.write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
