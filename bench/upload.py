"""Upload to first pixel of a large mesh: a generated OBJ (positions, UVs,
normals; a height field of `--grid`^2 quads = 2 grid^2 triangles, 2M by
default) and a scene naming it, sent to a fresh `rayfarm serve` (embedded
executor, SQLite, a temporary data dir, one render process).

    python bench/upload.py                 # 2M triangles
    python bench/upload.py --grid 300      # 180k triangles

Measured: the OBJ's size; the upload (POST /scenes: receive, parse the OBJ,
build the mesh asset, store it) in seconds; the job (64 x 64, 1 spp, one
tile: a render process builds the scene from the asset, its BVH, and traces)
from POST /jobs to its first finished unit; so upload-to-first-pixel; the
peak resident set of the service process and, separately, of every process
under it (the upload's checking child, the render process), polled every
50 ms from /proc (the upload child lives for less than a second at small
sizes: its peak is then a lower bound). A tiny upload and job first start
the upload checker's forkserver and load the kernels. Figures recorded in docs/hardening.md.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from embedded import embedded_service, rayfarm_script  # noqa: E402
from memory import status  # noqa: E402 (the same /proc reader)


def write_obj(path: Path, grid: int) -> int:
    """A height field of grid x grid quads (two triangles each); returns triangles."""
    n = grid + 1
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    z = 0.1 * np.sin(6 * x) * np.cos(5 * y)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i = (np.arange(grid)[:, None] * n + np.arange(grid)[None, :]).ravel() + 1
    with path.open("w") as fh:
        np.savetxt(fh, v, fmt="v %.6f %.6f %.6f")
        np.savetxt(fh, (v[:, :2] + 1) / 2, fmt="vt %.6f %.6f")
        np.savetxt(fh, np.tile([0.0, 0.0, 1.0], (len(v), 1)), fmt="vn %g %g %g")
        quads = np.stack([i, i + 1, i + n + 1, i + n], axis=1)
        np.savetxt(fh, np.repeat(quads, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d %d/%d/%d")
    return 2 * grid * grid


def descendants(pid: int) -> list[int]:
    kids: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(entry.name))
    out, stack = [], [pid]
    while stack:
        for child in kids.get(stack.pop(), []):
            out.append(child)
            stack.append(child)
    return out


class PeakWatch:
    """The largest VmHWM seen of a process and, apart, of its descendants."""

    def __init__(self, pid: int):
        self.pid, self.service, self.children = pid, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.service = max(self.service, status(self.pid)["VmHWM"])
            for child in descendants(self.pid):
                self.children = max(self.children, status(child)["VmHWM"])
            time.sleep(0.05)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid", type=int, default=1000, help="quads per side (2 grid^2 triangles)")
    parser.add_argument("--rayfarm", default=rayfarm_script())
    args = parser.parse_args()
    import httpx

    work = Path(tempfile.mkdtemp(prefix="rayfarm-upload-"))
    data_dir = work / "data"
    try:
        obj = work / "big.obj"
        t0 = time.perf_counter()
        triangles = write_obj(obj, args.grid)
        print(f"{obj.name}: {triangles} triangles, {obj.stat().st_size / 1e6:.0f} MB "
              f"(written in {time.perf_counter() - t0:.0f} s)")
        scene = work / "big.json"
        scene.write_text('{"camera": {"origin": [0, -2.5, 2.5], "target": [0, 0, 0], "up": [0, 0, 1],'
                         ' "fov": 45, "width": 64, "height": 64}, "materials": {"m": {"type": '
                         '"diffuse", "albedo": 0.7}}, "shapes": [{"type": "mesh", "material": "m",'
                         ' "file": "big.obj"}, {"type": "rectangle", "material": "m", "to_world":'
                         ' [{"translate": [0, 0, 3]}], "flip_normals": true, "emitter": {"type": '
                         '"area", "radiance": [5, 5, 5]}}]}')
        with embedded_service(workers=1, data_dir=data_dir, command=[args.rayfarm],
                              env={"RAYFARM_MAX_UPLOAD_BYTES": str(1 << 30)}) as server, \
                httpx.Client(base_url=server.base, timeout=900, headers=server.headers) as client:
            # a first upload and job start the upload checker's forkserver and
            # load the render process's kernels: not what is measured
            tiny = work / "tiny"
            tiny.mkdir()
            write_obj(tiny / "big.obj", 2)
            with scene.open("rb") as s, (tiny / "big.obj").open("rb") as o:
                warm = client.post("/scenes", files=[("scene", ("big.json", s)),
                                                     ("files", ("big.obj", o))])
            if warm.status_code >= 300:
                raise RuntimeError(f"warm-up upload refused: {warm.status_code} {warm.text}")
            warm_job = client.post("/jobs", json={"scene": warm.json()["id"], "method": "path",
                                                  "spp": 1, "depth": 2, "tile_size": 64,
                                                  "seed": 1, "progressive": False}).json()
            while client.get(f"/jobs/{warm_job['id']}").json()["status"] not in (
                    "done", "failed", "canceled"):
                time.sleep(0.1)
            time.sleep(2.0)
            base = status(server.pid)["VmRSS"]
            watch = PeakWatch(server.pid)
            t0 = time.perf_counter()
            with scene.open("rb") as s, obj.open("rb") as o:
                response = client.post("/scenes", files=[("scene", ("big.json", s)),
                                                         ("files", ("big.obj", o))])
            upload = time.perf_counter() - t0
            if response.status_code >= 300:
                raise RuntimeError(f"upload refused: {response.status_code} {response.text}")
            info = response.json()
            t1 = time.perf_counter()
            job = client.post("/jobs", json={"scene": info["id"], "method": "path", "spp": 1,
                                             "depth": 2, "tile_size": 64, "seed": 1,
                                             "progressive": False})
            if job.status_code != 201:
                raise RuntimeError(f"job refused: {job.status_code} {job.text}")
            job_id = job.json()["id"]
            while True:
                state = client.get(f"/jobs/{job_id}").raise_for_status().json()
                if state["progress"]["units_done"] >= 1 or state["status"] in ("failed",
                                                                               "canceled"):
                    break
                time.sleep(0.05)
            first = time.perf_counter() - t1
            watch.stop()
            if state["status"] in ("failed", "canceled"):
                raise RuntimeError(f"job {state['status']}: {state.get('error')}")
        stored = sum(p.stat().st_size for p in (data_dir / "store").rglob("*") if p.is_file())
        print(f"upload (POST /scenes): {upload:.1f} s; scene {info['id'][:12]}: "
              f"{info['triangles']} triangles, text {info['bytes']} bytes, store "
              f"{stored / 1e6:.0f} MB")
        print(f"job to its first unit: {first:.1f} s; upload to first pixel: "
              f"{upload + first:.1f} s")
        print(f"peak resident: service {watch.service / 1e6:.0f} MB (before: {base / 1e6:.0f}"
              f" MB), its largest child (upload check, render process) "
              f"{watch.children / 1e6:.0f} MB")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
