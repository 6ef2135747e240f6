"""How the API answers while large scenes are uploaded: GET /jobs latency
(p50, p99, max) before, during and after concurrent uploads of big .obj
meshes, against a real `rayfarm serve` (embedded: SQLite, local pool).

    python bench/api_latency.py                        # 3 uploads of a 59 MiB .obj
    python bench/api_latency.py --uploads 3 --mib 59 --jobs 50 --tree /path/to/checkout

The service runs from `--tree` (default: this checkout) with `python -m
service serve`, in a fresh data dir. It first gets `--jobs` small finished jobs
(so GET /jobs has something to list), then one client polls GET /jobs
back to back (`--gap` seconds apart) through three phases: idle for
`--idle` seconds, while `--uploads` uploads run at once (each a different
mesh of about `--mib` MiB, so none is deduplicated), and `--idle` seconds
after the last upload answered (thumbnails render then). The figures go to
docs/operations.md ("The API during large uploads").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from embedded import embedded_service  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "rf_bench_api_latency_0123456789abcdef"
HEADERS = {"Authorization": f"Bearer {TOKEN}"}
SCENE = {
    "description": "a box room with a large grid mesh from an OBJ file",
    "camera": {"origin": [0, 0, 3.9], "target": [0, 0, 0], "fov": 45, "width": 256,
               "height": 192},
    "materials": {"white": {"type": "diffuse", "albedo": 0.7}},
    "shapes": [
        {"type": "rectangle", "material": "white",
         "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": -90}}, {"translate": [0, -1, 0]}]},
        {"type": "rectangle", "material": "white",
         "to_world": [{"scale": [0.3, 0.3, 1]}, {"rotate": {"axis": [1, 0, 0], "angle": 90}},
                      {"translate": [0, 0.99, 0]}],
         "emitter": {"type": "area", "radiance": [15, 15, 15]}},
        {"type": "mesh", "file": "grid.obj", "material": "white",
         "to_world": [{"scale": [0.6, 0.6, 0.6]}]},
    ],
}


def grid_obj(mib: float) -> bytes:
    """A bumpy n x n grid as Wavefront OBJ text of about `mib` MiB (2 (n-1)^2 triangles)."""
    n = max(int((mib * 2**20 / 75) ** 0.5), 2)  # ~31 bytes a vertex line, ~22 a face line
    u = np.linspace(-1.0, 1.0, n)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = 0.05 * np.sin(9 * x) * np.cos(7 * y)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel() + 1
    faces = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    out = tempfile.SpooledTemporaryFile()
    np.savetxt(out, vertices, fmt="v %.6f %.6f %.6f")
    np.savetxt(out, faces, fmt="f %d %d %d")
    out.seek(0)
    return out.read()


class Poller(threading.Thread):
    """GET /jobs back to back; (monotonic time, seconds, status) of each answer."""

    def __init__(self, base: str, gap: float):
        super().__init__(daemon=True)
        self.base, self.gap = base, gap
        self.samples: list[tuple[float, float, int]] = []
        self.done = threading.Event()

    def run(self) -> None:
        with httpx.Client(headers=HEADERS, timeout=60) as client:
            while not self.done.is_set():
                sent = time.monotonic()
                status = client.get(f"{self.base}/jobs").status_code
                self.samples.append((sent, time.monotonic() - sent, status))
                time.sleep(self.gap)

    def between(self, start: float, end: float) -> list[float]:
        return [s for t, s, _ in self.samples if start <= t < end]


def summary(latencies: list[float]) -> str:
    if not latencies:
        return "no samples"
    ms = sorted(x * 1000 for x in latencies)
    p99 = ms[min(len(ms) - 1, int(round(0.99 * (len(ms) - 1))))]
    return (f"n={len(ms):4d}  p50 {statistics.median(ms):7.1f} ms  p99 {p99:7.1f} ms  "
            f"max {ms[-1]:7.1f} ms")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tree", type=Path, default=ROOT, help="the checkout to serve")
    parser.add_argument("--uploads", type=int, default=3)
    parser.add_argument("--mib", type=float, default=59.0, help="size of each .obj")
    parser.add_argument("--jobs", type=int, default=50, help="finished jobs GET /jobs lists")
    parser.add_argument("--idle", type=float, default=5.0, help="seconds before and after")
    parser.add_argument("--gap", type=float, default=0.02, help="seconds between two GETs")
    parser.add_argument("--workers", type=int, default=1, help="RAYFARM_LOCAL_WORKERS")
    parser.add_argument("--trace", type=Path, help="write every GET's (time, seconds) here "
                                                   "(JSON), times from the uploads' start")
    args = parser.parse_args()

    obj = grid_obj(args.mib)
    triangles = obj.count(b"\nf ")
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores; tree "
          f"{args.tree}; {args.uploads} uploads of {len(obj) / 2**20:.1f} MiB .obj "
          f"({triangles} triangles); {args.jobs} finished jobs listed", flush=True)
    scratch = Path(tempfile.mkdtemp(prefix="rayfarm-api-latency-"))
    try:
        with embedded_service(workers=args.workers, data_dir=scratch / "data", token=TOKEN,
                              command=[sys.executable, "-m", "service"], cwd=args.tree,
                              env={"PYTHONPATH": str(args.tree)}, loglevel="warning",
                              log=scratch / "serve.log", timeout=600) as server:
            base = server.base
            with httpx.Client(base_url=base, headers=HEADERS, timeout=60) as client:
                ids = [client.post("/jobs", json={"scene": "cornell-box", "method": "path",
                                                  "spp": 1, "depth": 2, "width": 16,
                                                  "height": 16, "seed": i}).json()["id"]
                       for i in range(args.jobs)]
                while any(client.get(f"/jobs/{i}").json()["status"] not in ("done", "failed")
                          for i in ids):
                    time.sleep(0.5)
            poller = Poller(base, args.gap)
            poller.start()
            t0 = time.monotonic()
            time.sleep(args.idle)
            t1 = time.monotonic()
            results: list[tuple[int, float, str]] = []

            def upload(k: int) -> None:
                body = b"# upload %d\n" % k + obj  # a comment line: new content, the same mesh
                scene = json.dumps(dict(SCENE, name=f"grid-{k}")).encode()
                started = time.monotonic()
                with httpx.Client(headers=HEADERS, timeout=600) as client:
                    response = client.post(f"{base}/scenes", files=[
                        ("scene", ("grid.json", scene, "application/json")),
                        ("files", ("grid.obj", body, "text/plain"))])
                results.append((response.status_code, time.monotonic() - started,
                                response.headers.get("retry-after", "")))
            threads = [threading.Thread(target=upload, args=(k,)) for k in range(args.uploads)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            t2 = time.monotonic()
            time.sleep(args.idle)
            t3 = time.monotonic()
            poller.done.set()
            poller.join()
            print(f"GET /jobs idle          {summary(poller.between(t0, t1))}")
            print(f"GET /jobs during uploads {summary(poller.between(t1, t2))}  ({t2 - t1:.1f} s)")
            print(f"GET /jobs after         {summary(poller.between(t2, t3))}")
            if args.trace:
                args.trace.write_text(json.dumps({
                    "gets": [(round(t - t1, 3), round(s, 4)) for t, s, _ in poller.samples],
                    "uploads_done": round(t2 - t1, 3)}))
            statuses = sorted(s for _, _, s in poller.samples)
            print(f"GET /jobs statuses: {dict((s, statuses.count(s)) for s in set(statuses))}")
            for status, seconds, retry in sorted(results):
                print(f"upload: {status} in {seconds:.1f} s" + (f" (Retry-After {retry})"
                                                                if retry else ""))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
