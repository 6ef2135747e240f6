"""Throughput of the renderer on `cornell-box`, the farm's overhead, and Mitsuba 3.

    python bench/throughput.py                        # depth 7, 256x256, 64 spp, all cores
    python bench/throughput.py --spp 256 --repeat 3 --workers 2

Three measurements, each after a warm-up (compilation is never timed), best
of `--repeat`:

1. farm path: the job through plan -> units -> merge on the local process
   pool (`renderer.render`, one single-threaded renderer per core; the shape
   of the service's embedded executor). Camera samples/s and rays/s come
   from the merged film's stats over the wall-clock time.
1b. service: the same job submitted over HTTP to a `rayfarm serve` process
   (embedded executor, SQLite ledger, a temporary data dir), timed from the
   POST until GET /jobs/{id} says done: planning, the ledger, storing unit
   films, the running preview, merging and writing the EXR and PNGs
   included; once planned as one pass per tile and once progressively (the
   default: passes of 1, 1, 2, 4, ... spp per tile, many more units).
2. kernel: one `renderer.run_unit` over the whole image in this process,
   Numba threads = all cores. farm overhead = farm wall time / kernel wall time.
3. Mitsuba 3 (only if importable; `pip install -e '.[mitsuba]'`): the same
   scene (built by bench/mitsuba_reference.py from our scene document, box
   filter, independent sampler, max_depth = depth + 1, no Russian roulette)
   in a subprocess, variant llvm_ad_rgb if it works, else scalar_rgb.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def best_of(repeat: int, fn):
    """Run fn() `repeat` times; return (shortest wall time, result of that run)."""
    best = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        seconds = time.perf_counter() - t0
        if best is None or seconds < best[0]:
            best = (seconds, result)
    return best


def bench_farm(spec, workers: int, repeat: int) -> dict:
    from renderer import LocalPool, RenderSpec, render

    with LocalPool(workers) as pool:
        warm = RenderSpec(method=spec.method, spp=1, depth=spec.depth, width=spec.width,
                          height=spec.height, tile_size=spec.tile_size, seed=spec.seed)
        render("cornell-box", warm, pool=pool)  # every child has loaded its kernels
        seconds, film = best_of(repeat, lambda: render("cornell-box", spec, pool=pool))
    return {"seconds": seconds, "samples": film.stats["samples"], "rays": film.stats["rays"],
            "unit_seconds": film.stats["seconds"], "mean": film.mean().mean(axis=(0, 1)).tolist()}


def bench_service(spec, workers: int, repeat: int) -> dict:
    """Submit the job to a fresh `rayfarm serve` and time it until done."""
    import socket
    import tempfile

    import httpx

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    data_dir = tempfile.mkdtemp(prefix="rayfarm-bench-")
    env = {**os.environ, "RAYFARM_DATA_DIR": data_dir, "RAYFARM_LOCAL_WORKERS": str(workers),
           "RAYFARM_BROKER_URL": "", "RAYFARM_DATABASE_URL": ""}
    rayfarm = Path(sys.executable).with_name("rayfarm")
    server = subprocess.Popen([str(rayfarm), "serve", "--host", "127.0.0.1", "--port", str(port)],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base, timeout=30) as client:
            deadline = time.monotonic() + 300
            while True:
                try:
                    if client.get("/healthz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline:
                    raise RuntimeError("rayfarm serve did not come up")
                time.sleep(0.2)

            def run(spp: int, seed: int, progressive: bool = False) -> float:
                body = {"scene": "cornell-box", "method": spec.method, "spp": spp, "depth": spec.depth,
                        "tile_size": spec.tile_size, "seed": seed, "width": spec.width,
                        "height": spec.height, "progressive": progressive}
                t0 = time.perf_counter()
                job = client.post("/jobs", json=body).raise_for_status().json()
                while True:
                    state = client.get(f"/jobs/{job['id']}").raise_for_status().json()
                    if state["status"] == "done":
                        return time.perf_counter() - t0
                    if state["status"] in ("failed", "canceled"):
                        raise RuntimeError(f"benchmark job {state['status']}: {state.get('error')}")
                    time.sleep(0.02)

            run(1, 0)  # warm-up: every pool process has loaded its kernels
            seconds = min(run(spec.spp, spec.seed) for _ in range(repeat))
            progressive = min(run(spec.spp, spec.seed, True) for _ in range(repeat))
    finally:
        server.terminate()
        server.wait(60)
    return {"seconds": seconds, "progressive_seconds": progressive,
            "samples": spec.width * spec.height * spec.spp}


def bench_kernel(spec, threads: int, repeat: int) -> dict:
    import numba

    from renderer import RenderSpec, Unit, load_scene, run_unit, warm_up

    numba.set_num_threads(threads)
    warm_up()
    scene = load_scene("cornell-box")
    warm = RenderSpec(method=spec.method, spp=1, depth=spec.depth, width=spec.width,
                      height=spec.height, tile_size=spec.tile_size, seed=spec.seed)
    run_unit(scene, warm, Unit(0, 0, 0, spec.width, spec.height, 0, 1))
    whole = Unit(0, 0, 0, spec.width, spec.height, 0, spec.spp)
    seconds, film = best_of(repeat, lambda: run_unit(scene, spec, whole))
    return {"seconds": seconds, "samples": film.stats["samples"], "rays": film.stats["rays"]}


def bench_mitsuba(args) -> dict:
    """Run Mitsuba in a child process (Dr.Jit's LLVM and Numba's stay apart)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--mitsuba-child", "--spp", str(args.spp),
           "--depth", str(args.depth), "--size", str(args.size), "--repeat", str(args.repeat)]
    if args.mitsuba_variant:
        cmd += ["--mitsuba-variant", args.mitsuba_variant]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["no output"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def mitsuba_child(args) -> None:
    sys.path.insert(0, str(HERE))
    from mitsuba_reference import choose_variant, mitsuba_scene_dict

    import mitsuba as mi
    import numpy as np

    from renderer import resolve_document

    variant = choose_variant(args.mitsuba_variant)
    doc = resolve_document("cornell-box")
    doc["camera"]["width"] = doc["camera"]["height"] = args.size
    scene = mi.load_dict(mitsuba_scene_dict(doc, args.depth))
    np.array(mi.render(scene, spp=args.spp, seed=0))  # warm-up: JIT compilation
    seed = iter(range(1, 1 + args.repeat))
    seconds, image = best_of(args.repeat, lambda: np.array(mi.render(scene, spp=args.spp,
                                                                     seed=next(seed))))
    print(json.dumps({"variant": variant, "version": mi.__version__, "seconds": seconds,
                      "samples": args.size * args.size * args.spp,
                      "mean": image[..., :3].mean(axis=(0, 1)).tolist()}))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--size", type=int, default=256, help="image width and height")
    parser.add_argument("--repeat", type=int, default=1, help="timed runs; the best is reported")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="pool processes and kernel threads (default: all cores)")
    parser.add_argument("--tile-size", type=int, default=64)
    parser.add_argument("--no-mitsuba", action="store_true", help="skip Mitsuba even if installed")
    parser.add_argument("--mitsuba-variant", default=None)
    parser.add_argument("--mitsuba-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.mitsuba_child:
        mitsuba_child(args)
        return 0

    from renderer import RenderSpec

    spec = RenderSpec(method="path", spp=args.spp, depth=args.depth, width=args.size,
                      height=args.size, tile_size=args.tile_size, seed=1).validate()
    print(f"cornell-box, method path, depth {args.depth}, {args.size}x{args.size}, "
          f"{args.spp} spp, {args.workers} workers/threads, best of {args.repeat}")

    farm = bench_farm(spec, args.workers, args.repeat)
    print(f"farm path (local pool): {farm['seconds']:.3f} s  "
          f"{farm['samples'] / farm['seconds'] / 1e6:.3f} M camera samples/s  "
          f"{farm['rays'] / farm['seconds'] / 1e6:.3f} M rays/s  "
          f"(sum of unit times {farm['unit_seconds']:.3f} s)")
    print(f"  image mean R G B = {' '.join(f'{v:.6f}' for v in farm['mean'])}")

    service = bench_service(spec, args.workers, args.repeat)
    print(f"service (rayfarm serve, embedded executor, submit -> done), one pass: "
          f"{service['seconds']:.3f} s  "
          f"{service['samples'] / service['seconds'] / 1e6:.3f} M camera samples/s")
    print(f"service, progressive passes: {service['progressive_seconds']:.3f} s  "
          f"{service['samples'] / service['progressive_seconds'] / 1e6:.3f} M camera samples/s")

    kernel = bench_kernel(spec, args.workers, args.repeat)
    print(f"kernel, whole image in-process: {kernel['seconds']:.3f} s  "
          f"{kernel['samples'] / kernel['seconds'] / 1e6:.3f} M camera samples/s  "
          f"{kernel['rays'] / kernel['seconds'] / 1e6:.3f} M rays/s")
    print(f"farm overhead: local pool time / kernel time = {farm['seconds'] / kernel['seconds']:.2f}x; "
          f"service time / kernel time = {service['seconds'] / kernel['seconds']:.2f}x "
          f"(progressive {service['progressive_seconds'] / kernel['seconds']:.2f}x)")

    if args.no_mitsuba:
        return 0
    if importlib.util.find_spec("mitsuba") is None:
        print("mitsuba: not installed (pip install -e '.[mitsuba]'); skipped")
        return 0
    mts = bench_mitsuba(args)
    if "error" in mts:
        print(f"mitsuba: failed: {mts['error']}")
        return 0
    mts_rate = mts["samples"] / mts["seconds"]
    farm_rate = farm["samples"] / farm["seconds"]
    print(f"mitsuba {mts['version']} ({mts['variant']}): {mts['seconds']:.3f} s  "
          f"{mts_rate / 1e6:.3f} M camera samples/s")
    print(f"  image mean R G B = {' '.join(f'{v:.6f}' for v in mts['mean'])}")
    print(f"rayfarm farm path / mitsuba samples/s = {farm_rate / mts_rate:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
