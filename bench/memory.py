"""Peak memory of one job: the service's and its render process's, per frame size.

    python bench/memory.py                                  # the default jobs
    python bench/memory.py --jobs raster:1024:1024:1024 raster:2048:2048:2048
    python bench/memory.py --jobs path-mis:4096:4096:64 --save after.json
    python bench/memory.py --jobs ... --compare before.json # both side by side

A job is `method:width:height:tile_size[:spp]` (spp 1 unless given), on
cornell-box, depth 3, one pass, submitted as the admin. Each job runs in a
fresh `rayfarm serve` (embedded executor, SQLite, a temporary data dir,
--workers render processes: 1 by default, so one process renders every unit
and its peak is a unit's), after a warm-up job of 4 x 4 pixels (kernels
loaded, the merge's imports done). Then the peak resident set of the service
and of each render process is reset (Linux: `5 > /proc/PID/clear_refs`), the
job is submitted and waited for, and read back from /proc:

- service rise: the service's VmHWM after the job minus its VmRSS before;
- service kept: its VmRSS 3 s after the job minus the same;
- render: the render process's VmHWM during the job minus its VmRSS before
  (the largest over the render processes);

and, where the checkout has renderer/memory.py, its figures for the job
(the service's share with --workers processes, a unit's render process).

To measure another checkout (the code before a change), run this file from
that checkout's directory with its `rayfarm` on the path (`--rayfarm`), e.g.
a `git worktree` of the older commit sharing this .venv. `--env NAME=VALUE`
passes settings to the service (`RAYFARM_LIMITS_ADMIN__...` to let a job
through that the limits would refuse: the checkout must know the setting).
Figures recorded are in docs/hardening.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from embedded import embedded_service, rayfarm_script  # noqa: E402

DEFAULT_JOBS = ["raster:1024:1024:1024", "raster:2048:2048:2048"]


def status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process in bytes (0 when it is gone)."""
    out = {"VmRSS": 0, "VmHWM": 0}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in out:
                out[key] = int(value.split()[0]) * 1024
    except OSError:
        pass
    return out


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid`."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def reset_peak(pid: int) -> None:
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")
    except OSError:
        pass


def parse_job(text: str) -> dict:
    parts = text.split(":")
    method, width, height, tile = parts[0], int(parts[1]), int(parts[2]), int(parts[3])
    spp = int(parts[4]) if len(parts) > 4 else 1
    return {"scene": "cornell-box", "method": method, "spp": spp, "depth": 3, "width": width,
            "height": height, "tile_size": tile, "seed": 1, "progressive": False}


def run_job(rayfarm: str, body: dict, workers: int, env_extra: dict) -> dict:
    import httpx

    # the temporary data dir goes with the service: a 4096^2 job's films are gigabytes
    with embedded_service(workers=workers, env=env_extra, command=[rayfarm]) as server, \
            httpx.Client(base_url=server.base, timeout=60, headers=server.headers) as client:

        def submit(job: dict) -> tuple[dict, float]:
            t0 = time.perf_counter()
            response = client.post("/jobs", json=job)
            if response.status_code != 201 and response.status_code != 200:
                return {"status": "refused", "error": response.text}, 0.0
            job_id = response.json()["id"]
            while True:
                state = client.get(f"/jobs/{job_id}").raise_for_status().json()
                if state["status"] in ("done", "failed", "canceled"):
                    return state, time.perf_counter() - t0
                time.sleep(0.25)

        warm, _ = submit({**body, "width": 4, "height": 4, "tile_size": 4})
        if warm["status"] != "done":
            raise RuntimeError(f"warm-up job {warm['status']}: {warm.get('error')}")
        time.sleep(1.0)
        renderers = children(server.pid)
        before = {pid: status(pid)["VmRSS"] for pid in [server.pid, *renderers]}
        for pid in before:
            reset_peak(pid)
        state, seconds = submit(body)
        peaks = {pid: status(pid)["VmHWM"] for pid in before}
        time.sleep(3.0)
        kept = status(server.pid)["VmRSS"]
        render = max((peaks[p] - before[p] for p in renderers if peaks[p]), default=0)
        return {"job": body, "status": state["status"], "error": state.get("error"),
                "seconds": round(seconds, 2),
                "service_base": before[server.pid],
                "service_rise": peaks[server.pid] - before[server.pid],
                "service_kept": kept - before[server.pid],
                "render_rise": render,
                "render_base": max((before[p] for p in renderers), default=0)}


def predicted(body: dict, workers: int) -> dict:
    """renderer.memory's figures for the job (a checkout without it: none)."""
    try:
        from renderer import METHODS, RenderSpec
        from renderer.memory import job_memory
    except ImportError:
        return {}
    spec = RenderSpec(**{k: v for k, v in body.items() if k not in ("scene", "progressive")})
    units = len(METHODS[spec.method].make_plan(spec, body["progressive"]))
    mem = job_memory(spec, progressive=body["progressive"])
    return {"predicted_unit": mem.unit,
            "predicted_service": mem.service(workers, min(units, 16 * workers))}


def name_of(job: dict) -> str:
    return f"{job['method']} {job['width']}x{job['height']} tile {job['tile_size']} spp {job['spp']}"


def mb(n: int | None) -> str:
    return "-" if n is None else f"{n / 1e6:,.0f} MB"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", nargs="+", default=DEFAULT_JOBS)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--rayfarm", default=rayfarm_script())
    parser.add_argument("--env", nargs="*", default=[], help="NAME=VALUE for the service")
    parser.add_argument("--label", default="this checkout")
    parser.add_argument("--save", type=Path)
    parser.add_argument("--compare", type=Path)
    args = parser.parse_args()
    env = dict(item.split("=", 1) for item in args.env)
    results = []
    for text in args.jobs:
        result = run_job(args.rayfarm, parse_job(text), args.workers, env)
        result.update(predicted(result["job"], args.workers))
        results.append(result)
        figures = (f" (renderer.memory: service {mb(result['predicted_service'])}, unit "
                   f"{mb(result['predicted_unit'])})" if "predicted_unit" in result else "")
        print(f"{name_of(result['job'])}: {result['status']} in {result['seconds']} s; service "
              f"+{mb(result['service_rise'])} peak, +{mb(result['service_kept'])} kept; "
              f"render process +{mb(result['render_rise'])}{figures}"
              + (f" ({result['error'][:200]})" if result["status"] != "done" else ""),
              flush=True)
    if args.save:
        args.save.write_text(json.dumps({"label": args.label, "results": results}, indent=1))
    if args.compare:
        old = json.loads(args.compare.read_text())
        by_name = {name_of(r["job"]): r for r in old["results"]}
        print(f"\n| job | service peak: {old['label']} | {args.label} | service kept: "
              f"{old['label']} | {args.label} | render process: {old['label']} | {args.label} |")
        print("|---|---|---|---|---|---|---|")
        for r in results:
            o = by_name.get(name_of(r["job"]), {})
            print(f"| {name_of(r['job'])} | {mb(o.get('service_rise'))} | {mb(r['service_rise'])} "
                  f"| {mb(o.get('service_kept'))} | {mb(r['service_kept'])} "
                  f"| {mb(o.get('render_rise'))} | {mb(r['render_rise'])} |")


if __name__ == "__main__":
    main()
