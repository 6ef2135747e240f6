"""How soon rayfarm reaches a given error, next to Mitsuba 3, and what the farm adds.

    python bench/throughput.py                       # the full table (about 30 min with references)
    python bench/throughput.py --scenes cornell-box --spp 64 --samplers default --no-farm

The figure that counts is efficiency, 1 / (MSE x seconds): a sampler or a
Russian roulette that makes samples cheap but noisy does not win by it.

1. References (cached in --refs, made once): each renderer renders each
   scene at --ref-spp with i.i.d. samples (rayfarm `path-mis`, sampler
   `random`; Mitsuba `path`, independent sampler, in 16 passes, no Russian
   roulette), and keeps the mean and the variance of that mean per pixel.
   Each renderer is measured against its own reference: the glossy plates of
   veach-mis are not the same BSDF in both (mitsuba_reference.py). The two
   cornell-box references are compared with each other as a check.
2. MSE over the pixels that do not see an emitter directly, minus the
   reference's own variance of the mean: E[(x - r)^2] = MSE(x) + Var(r) for
   an independent reference, so the estimate does not flatter the noisier
   renderer by the reference's noise. Each render is one in-process kernel
   call over the whole image on --workers Numba threads, warm (compilation
   is never timed); median time and mean MSE of --repeat renders with
   different seeds.
3. Mitsuba 3 (`pip install -e '.[mitsuba]'`, `llvm_ad_rgb` when it JITs,
   else `scalar_rgb`) with its default settings (independent sampler,
   Russian roulette from depth 5), max_depth = depth + 1, box filter, in a
   child process: Dr.Jit's LLVM and Numba's stay apart. The child renders
   on request, and the renders interleave: each repeat renders Mitsuba,
   then each of rayfarm's samplers, so a drift of this VM's speed (up to a
   third within minutes, seen here) weighs on every row alike.
4. Scaling: the default's samples/s on 1 thread and on --workers threads,
   and through the local process pool with 1 and --workers processes.
5. BVH traversal alone, rays/s per core (bench/traversal.py), on the
   scenes here and on a 100 k-triangle mesh scene (bench/heavy_mesh.py).
6. Farm overhead: a job of about 10 s and one of about 1 s submitted over
   HTTP to `rayfarm serve` (embedded executor, SQLite, a temporary data
   dir), timed from the POST until the job is done (median of 5), one pass
   and progressive, with the service process's CPU seconds, each service
   run right after the same job on the pool (this VM's speed drifts by up
   to a third within minutes: run in blocks, the two drifted apart). Against two
   baselines: the kernel rendering the same image in-process on --workers
   Numba threads, and `renderer.render` running the job's plan on a local
   pool of --workers processes without the service. Service / pool - 1 is
   the service's own share (HTTP, the ledger, storing films, previews,
   events); service / kernel - 1 the whole farm's (tiles, processes, the
   pool idling at the end as well).

The table goes to stdout and, in Markdown, to --out (docs/throughput.md).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SIZES = {"cornell-box": (256, 256), "veach-mis": (256, 144)}
REF_SEED = 987654


NOTES = """## Reading the table

- Mitsuba renders with its defaults (independent sampler, Russian roulette
  from depth 5, survival = the throughput's largest channel, at most
  0.95); rayfarm with `path-mis`, Russian roulette from the third vertex,
  survival = min(1, 2 x the path throughput's largest channel): the
  `roulette` option, 2 by default (renderer/integrators/path.py).
  Where the roulette starts was measured with survival = 1 x the largest
  channel (pbrt-v4's and Mitsuba's rule): with `random` on cornell-box at
  256 spp, efficiency relative to the third vertex: the second 0.98, the
  fourth 0.96, the fifth 0.92, no roulette 0.70; with packets and `sobol`
  (2026-11-27), against Mitsuba at 16 / 64 / 256 spp: from the third
  vertex 1.27 / 1.41 / 1.92, the fourth 1.14 / 1.31 / 1.89, the sixth
  1.05 / 1.33 / 1.96. The survival's scale was measured later (2026-11-27,
  the eighth session, Zen 5, `sobol`, variance over 6-8 seeds and the
  median time, efficiency relative to scale 1 at 16 / 64 / 256 spp):
  cornell-box 1.5: +12 / +18 / +24 %, 2: +9 / +19 / +26 %, 3: +6 / +17 /
  +31 %, no roulette: -17 / -9 / +6 %; veach-mis 1.5: -6 / -1 / 0 %, 2:
  -7 / -9 / -3 %; at 64 spp door-ajar 1.5: +21 %, 2: +31 %, and
  cornell-caustic +11 % and +10 %. Scale 2 kept: a closed bright room's
  deep bounces are much of its image and of its error (below), and scale
  1 cut them hardest; where the error is direct light (veach-mis) longer
  paths only cost time.
- veach-mis: the MSE is dominated by the few pixels where the smooth plates
  reflect the two smallest lights (radiance 338 and 3040): there a sampler
  that stratifies the pixel footprint (every one but `random` and `nrooks`'
  unpaired dims) wins most. The glossy BSDFs differ slightly (Schlick
  Fresnel and height-correlated G2 here, no Fresnel and separable G in
  Mitsuba's `roughconductor`), so each renderer is measured against its own
  reference.
- `sobol` costs 5 % of `random`'s samples/s on cornell-box at 64 and
  256 spp, 13 % at 16 spp (4.33 / 4.30 / 3.83 M against 4.56 / 4.51 /
  4.42 M at 64 / 256 / 16 spp, AMD EPYC Zen 5, 2026-11-29's fourth
  session, since a bank's claim fills the pair tables its previous pixel
  drew: renderer/samplers/sobol.py); 8-11 % before
  (3.99 M against 4.36 M, Intel AVX-512, 2026-11-27's fifth session),
  18 % before its pair tables (3.27 M against 4.01 M, same machine):
  19-22 % with packets before (4.06 M against 5.01 M, Zen 5), about 13 %
  before packets (1.14 M against 1.30 M on one thread, 2026-11-26):
  packets made everything else cheaper. A `sobol` draw was a chain of
  about a hundred integer operations, 8-9 ns (pair key, memo tag, two
  scrambles, bit reversals) against 2-3 ns for `random`'s two hashes; the
  tile kernels now compute each pixel's pair tables in vectorized loops
  and read a draw from them, 2.1-2.4 ns, 4.0 ns with the tables' own
  cost (samplers/sobol.py, the same values to the bit). Its pairs below
  spp share one hashed permutation per pixel at rotated positions, which
  the tile kernels memoize per row (samplers/sobol.py), where every pair
  of every sample used to hash its own (22 %; 40 % before 2026-11-24). Its
  MSE is unchanged by that (cornell-box RMSE 0.02468 / 0.01076 / 0.00497
  at 16 / 64 / 256 spp against 0.02459 / 0.01078 / 0.00497 before), 45 %,
  56 % and 68 % lower than `random`'s.
- Where cornell-box's error is (`python bench/error_budget.py`, 64 spp,
  variance over 6 seeds): with `sobol` and survival scale 1, direct light
  8 % of the MSE, the second bounce 15 %, the third 24 %, bounces 4-7
  53 %; with scale 2, 11 / 23 / 23 / 43 % of an MSE a third lower; with
  `random` (scale 1), direct light 39 %. `sobol` divides the error of direct light by 11 and
  the second bounce's by 3, the deeper ones by 1.2-1.4: what is left is
  deep indirect light, where no 2D stratification reaches. Russian
  roulette from the fifth vertex instead of the third (measured with
  `sobol`, 64 spp, survival scale 1) lowers the MSE by 24 % and costs 32 %
  more time: the same efficiency; a survival scale of 2 from the third
  vertex lowers it by 33 % for 21 % more time (above). With `random` that
  scale gains only 16 % of MSE for 14 % more time: `sobol` leaves the
  deep bounces as most of the error, where roulette adds the most.
- The var channels are the variance of the mean of independent samples:
  exact for `random`, an overstatement for stratified samplers (README).
- The BVH is 4-wide, collapsed from a binned-SAH binary tree (renderer/
  bvh.py). Measured on one thread against the binary tree, whole renders
  at 16 spp: +12 % samples/s on cornell-box, +5 % on veach-mis, +20 % on
  cornell-mesh; float32 boxes were slower on all three (kept float64).
  Numba compiles with LLVM's SLP vectorizer off (numba PR 8852: it
  miscompiled), so the four slab tests of a node run as four scalar ones.
  Enabled (NUMBA_SLP_VECTORIZE=1) they compile to packed min/max. On
  2026-11-26 (AVX-512, one thread, 16 spp, 3 interleaved pairs of
  processes) that made cornell-box 9 % faster and veach-mis about 3 %, with
  the same bytes. The project does not rely on it: the switch is
  process-wide, Numba's disk cache does not key on it, and LLVM's SLP pass
  keeps having miscompilation reports. Measured again on 2026-11-28 (Zen 4,
  one thread, 64 spp, six interleaved pairs of processes), after the
  packet traversal's lane loops were written for the loop vectorizer:
  cornell-box -1.8 %, veach-mis -2.1 %, within the noise.
- Since 2026-11-27 the path tracer traces packets of 16 paths
  (renderer/kernels/packet.py, integrators/path.py): each bounce's rays,
  then its shadow rays, go through the BVH together, each node's and each
  leaf's tests one vectorized loop over the lanes, and a lane whose path
  ended takes the next sample at once. Traversal alone: 2-4x the rays/s of
  single rays on cornell-box and veach-mis. Whole renders (one thread,
  64 spp, `sobol`, interleaved runs): cornell-box +12 %, veach-mis +9 %,
  the 100 k-triangle mesh -7 % (its scattered bounce rays go one by one,
  and the lanes' bookkeeping remains). The same bytes as the single-path
  kernel it replaced, every strategy and sampler. What is left is shading:
  about half of a sample's time on cornell-box is the scalar per-lane code
  (light sample, BSDF, sampler, Russian roulette), the traversal a third."""


def cpu_description() -> str:
    """The CPU's model and widest vector extension: Mitsuba's LLVM backend
    uses the vector width the CPU has (AVX-512 doubles it over AVX2), rayfarm's
    scalar kernels do not, so the ratio between them depends on it."""
    model, flags = platform.processor() or "cpu", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model == (platform.processor() or "cpu"):
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    simd = next((f for f in ("avx512f", "avx2", "avx", "sse4_2", "asimd") if f in flags), "")
    return f"{model}, {simd}" if simd else model


def median(values):
    return float(np.median(np.asarray(values, dtype=float)))


# -- rayfarm ------------------------------------------------------------------------------

class Rayfarm:
    """In-process renders of whole images (one unit, rows over Numba threads)."""

    def __init__(self, scene_name: str, size: tuple[int, int], depth: int, threads: int):
        import numba

        from renderer import load_scene, warm_up

        numba.set_num_threads(threads)
        warm_up()
        self.name, (self.width, self.height), self.depth = scene_name, size, depth
        self.scene = load_scene(scene_name)

    def render(self, spp: int, sampler: str, seed: int, method: str = "path-mis", depth=None):
        from renderer import RenderSpec, Unit, merge, run_unit

        spec = RenderSpec(method=method, spp=spp, depth=self.depth if depth is None else depth,
                          width=self.width, height=self.height,
                          tile_size=max(self.width, self.height), seed=seed, sampler=sampler).validate()
        whole = Unit(0, 0, 0, self.width, self.height, 0, spp)
        t0 = time.perf_counter()
        part = run_unit(self.scene, spec, whole)
        seconds = time.perf_counter() - t0
        film = merge(self.width, self.height, [part])
        return film.mean(), film.variance_of_mean(), seconds, float(part.stats["rays"])


def rayfarm_reference(rf: Rayfarm, ref_spp: int, refs: Path):
    path = refs / f"rayfarm_{rf.name}_{rf.width}x{rf.height}_d{rf.depth}_spp{ref_spp}.npz"
    if not path.exists():
        print(f"  rendering rayfarm's reference: {ref_spp} spp ...", flush=True)
        mean, var, seconds, _ = rf.render(ref_spp, "random", REF_SEED)
        np.savez(path, mean=mean, var=var)
        print(f"  ... {seconds:.0f} s", flush=True)
    z = np.load(path)
    return z["mean"], z["var"]


def emitter_mask(rf: Rayfarm) -> np.ndarray:
    """True where no emitter is seen directly (a depth-0 render is black there)."""
    mean, _, _, _ = rf.render(4, "random", 1, depth=0)
    return mean.max(axis=2) <= 0.0


def mse_against(image, ref_mean, ref_var, mask) -> float:
    return float(((image - ref_mean)[mask] ** 2).mean() - ref_var[mask].mean())


# -- Mitsuba (child process) --------------------------------------------------------------

def mitsuba_child(args) -> None:
    """Render the reference if missing and warm up, print one JSON line; then
    render what each line on stdin asks ({"spp", "seed"}), one JSON line
    each ({"seconds", "image"}), until stdin closes. The parent asks for
    Mitsuba's renders between its own, so that a drift of this VM's speed
    weighs on both alike."""
    sys.path.insert(0, str(HERE))
    import mitsuba as mi
    from mitsuba_reference import choose_variant, mitsuba_scene_dict

    from renderer import resolve_document

    variant = choose_variant(args.mitsuba_variant)
    width, height = SIZES[args.scene]
    doc = resolve_document(args.scene)
    doc["camera"]["width"], doc["camera"]["height"] = width, height
    out = Path(args.mitsuba_child)
    ref = Path(args.refs) / f"mitsuba_{args.scene}_{width}x{height}_d{args.depth}_spp{args.ref_spp}.npz"
    if not ref.exists():
        scene = mi.load_dict(mitsuba_scene_dict(doc, args.depth, rr_depth=args.depth + 2))
        passes = 16
        images = [np.array(mi.render(scene, spp=args.ref_spp // passes, seed=REF_SEED + k),
                           dtype=np.float64)[..., :3] for k in range(passes)]
        stack = np.stack(images)
        np.savez(ref, mean=stack.mean(axis=0), var=stack.var(axis=0, ddof=1) / passes)
    scene = mi.load_dict(mitsuba_scene_dict(doc, args.depth))  # its default Russian roulette
    np.array(mi.render(scene, spp=4, seed=0))  # warm-up: JIT compilation
    print(json.dumps({"variant": variant, "version": mi.__version__, "reference": str(ref)}),
          flush=True)
    for count, line in enumerate(sys.stdin):
        ask = json.loads(line)
        t0 = time.perf_counter()
        image = np.array(mi.render(scene, spp=ask["spp"], seed=ask["seed"]),
                         dtype=np.float64)[..., :3]
        seconds = time.perf_counter() - t0
        name = out / f"mitsuba_{count}.npy"
        np.save(name, image)
        print(json.dumps({"seconds": seconds, "image": str(name)}), flush=True)


# Seconds between two timed renders: after a render, each renderer's worker
# threads spin for 10-20 ms before they sleep (measured: Dr.Jit's pool and
# Numba's OpenMP one), which would slow the other renderer's next render.
SETTLE = 0.1


class Mitsuba:
    """The Mitsuba child (`mitsuba_child`), rendering on request: `info` holds
    its variant, version and reference, or {"error": ...} if it failed."""

    def __init__(self, args, scene_name: str, tmp: Path):
        cmd = [sys.executable, str(Path(__file__).resolve()), "--mitsuba-child", str(tmp),
               "--scenes", scene_name, "--depth", str(args.depth), "--ref-spp", str(args.ref_spp),
               "--refs", str(args.refs)]
        if args.mitsuba_variant:
            cmd += ["--mitsuba-variant", args.mitsuba_variant]
        self.errors = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=self.errors, text=True)
        self.info = self._answer()

    def _answer(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            self.proc.wait()
            self.errors.seek(0)
            return {"error": (self.errors.read().strip().splitlines() or ["no output"])[-1]}
        return json.loads(line)

    def render(self, spp: int, seed: int) -> dict:
        self.proc.stdin.write(json.dumps({"spp": spp, "seed": seed}) + "\n")
        self.proc.stdin.flush()
        answer = self._answer()
        if "error" in answer:
            raise RuntimeError(f"Mitsuba's child failed: {answer['error']}")
        return answer

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait(60)
        self.errors.close()


# -- the farm -----------------------------------------------------------------------------

def pool_rate(scene_name: str, size, depth: int, spp: int, processes: int, sampler: str) -> float:
    """Camera samples/s of a job through plan -> units -> merge on the local pool."""
    from renderer import LocalPool, RenderSpec, render

    spec = RenderSpec(method="path-mis", spp=spp, depth=depth, width=size[0], height=size[1],
                      tile_size=64, seed=1, sampler=sampler)
    with LocalPool(processes) as pool:
        render(scene_name, RenderSpec(**{**spec.__dict__, "spp": 1}), pool=pool)  # warm children
        t0 = time.perf_counter()
        render(scene_name, spec, pool=pool)
        seconds = time.perf_counter() - t0
    return size[0] * size[1] * spp / seconds


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` so far (Linux /proc; NaN elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _pool_run(pool, scene_name: str, size, depth: int, spp: int, seed: int, progressive: bool,
              sampler: str) -> float:
    """Seconds of one job's plan rendered by `renderer.render` on `pool`, merged."""
    from renderer import RenderSpec, render

    spec = RenderSpec(method="path-mis", spp=spp, depth=depth, width=size[0], height=size[1],
                      tile_size=64, seed=seed, sampler=sampler)
    t0 = time.perf_counter()
    render(scene_name, spec, pool=pool, progressive=progressive)
    return time.perf_counter() - t0


PAIRS = 5  # pool-then-service pairs per job in the farm section


def farm_times(scene_name: str, size, depth: int, spp_list: list[int], workers: int,
               sampler: str) -> dict:
    """The same jobs through `renderer.render` on a local pool of `workers` processes
    (no service: same plan of 64-pixel tiles, same merge) and through a fresh
    `rayfarm serve` (embedded executor, `workers` processes), run alternately
    (pool, service, pool, service, ...), so that this VM's drifting speed
    weighs on both alike; PAIRS of each. Returns {spp: {progressive: (pool
    seconds, service seconds, the service process's CPU seconds: medians; the
    median over the pairs of service / pool - 1)}}."""
    import httpx

    from embedded import embedded_service
    from renderer import LocalPool

    with embedded_service(workers=workers, timeout=600) as server, \
            httpx.Client(base_url=server.base, timeout=30, headers=server.headers) as client, \
            LocalPool(workers) as pool:
        def service_run(spp: int, seed: int, progressive: bool) -> tuple[float, float]:
            body = {"scene": scene_name, "method": "path-mis", "spp": spp, "depth": depth,
                    "tile_size": 64, "seed": seed, "width": size[0], "height": size[1],
                    "sampler": sampler, "progressive": progressive}
            cpu0 = process_cpu_seconds(server.pid)
            t0 = time.perf_counter()
            job = client.post("/jobs", json=body).raise_for_status().json()
            # the job's event stream says `end` when it is final: no polling
            # (a GET every 10 ms cost this 2-core machine several percent)
            with client.stream("GET", f"/jobs/{job['id']}/events", timeout=None) as events:
                for line in events.iter_lines():
                    if line == "event: end":
                        break
            seconds = time.perf_counter() - t0
            cpu = process_cpu_seconds(server.pid) - cpu0
            state = client.get(f"/jobs/{job['id']}").raise_for_status().json()
            if state["status"] != "done":
                raise RuntimeError(f"benchmark job {state['status']}: {state.get('error')}")
            return seconds, cpu

        # warm-up: every process of both pools has loaded its kernels
        _pool_run(pool, scene_name, size, depth, 1, 0, False, sampler)
        service_run(1, 0, False)
        out: dict = {}
        for spp in spp_list:
            for progressive in (False, True):
                pools, services, cpus = [], [], []
                for seed in range(1, PAIRS + 1):
                    pools.append(_pool_run(pool, scene_name, size, depth, spp, seed,
                                           progressive, sampler))
                    seconds, cpu = service_run(spp, seed, progressive)
                    services.append(seconds)
                    cpus.append(cpu)
                share = median([b / a - 1 for a, b in zip(pools, services)])
                out.setdefault(spp, {})[progressive] = (median(pools), median(services),
                                                        median(cpus), share)
        return out


# -- the report ---------------------------------------------------------------------------

class Report:
    def __init__(self):
        self.lines: list[str] = []

    def __call__(self, line: str = "") -> None:
        print(line, flush=True)
        self.lines.append(line)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="cornell-box,veach-mis")
    parser.add_argument("--spp", default="16,64,256", type=lambda s: [int(v) for v in s.split(",")])
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--samplers", default="all", help="all, default, or a comma list")
    parser.add_argument("--repeat", type=int, default=3, help="renders per row (median time, mean MSE)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="Numba threads and pool processes (default: all cores)")
    parser.add_argument("--ref-spp", type=int, default=8192)
    parser.add_argument("--refs", default=str(Path.home() / ".cache" / "rayfarm-bench"))
    parser.add_argument("--out", default=None,
                        help="the Markdown report ('' for none; default docs/throughput.md, "
                             "none with --farm-only, which would overwrite the full report)")
    parser.add_argument("--no-mitsuba", action="store_true", help="skip Mitsuba even if installed")
    parser.add_argument("--no-farm", action="store_true", help="skip scaling and farm overhead")
    parser.add_argument("--no-traversal", action="store_true", help="skip the BVH traversal table")
    parser.add_argument("--farm-only", action="store_true",
                        help="only scaling and farm overhead (no references, no Mitsuba)")
    parser.add_argument("--mitsuba-variant", default=None)
    parser.add_argument("--mitsuba-child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = "" if args.farm_only else str(ROOT / "docs" / "throughput.md")
    Path(args.refs).mkdir(parents=True, exist_ok=True)
    if args.mitsuba_child:
        args.scene = args.scenes
        mitsuba_child(args)
        return 0

    from renderer import SAMPLERS, RenderSpec

    default = RenderSpec().sampler
    samplers = (list(SAMPLERS) if args.samplers == "all" else
                [default] if args.samplers == "default" else args.samplers.split(","))
    samplers = [default] + [s for s in samplers if s != default]
    report = Report()
    report("# Throughput and efficiency: rayfarm and Mitsuba 3")
    report()
    report(f"`python bench/throughput.py` on {platform.machine()} with {os.cpu_count()} cores "
           f"({cpu_description()}), {time.strftime('%Y-%m-%d')}: `path-mis`, depth "
           f"{args.depth} (Mitsuba max_depth {args.depth + 1}), box filter, {args.workers} "
           f"threads. RMSE over the pixels that do not see an emitter, against each renderer's "
           f"own {args.ref_spp}-spp reference, corrected for the reference's variance; "
           f"efficiency = 1 / (MSE x seconds), and its ratio to Mitsuba's at the same spp. "
           f"Median seconds and mean MSE of {args.repeat} renders. Default sampler: `{default}`.")
    mts_available = (not args.no_mitsuba and not args.farm_only
                     and importlib.util.find_spec("mitsuba") is not None)
    if not mts_available:
        report()
        report("Mitsuba: " + ("skipped (--no-mitsuba)" if args.no_mitsuba else
                              "not installed (pip install -e '.[mitsuba]'): no ratio column"))

    for scene_name in [] if args.farm_only else args.scenes.split(","):
        size = SIZES[scene_name]
        report()
        report(f"## {scene_name}, {size[0]}x{size[1]}")
        report()
        rf = Rayfarm(scene_name, size, args.depth, args.workers)
        mask = emitter_mask(rf)
        ref_mean, ref_var = rayfarm_reference(rf, args.ref_spp, Path(args.refs))
        mts_eff: dict[int, float] = {}
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            mts = Mitsuba(args, scene_name, Path(tmp)) if mts_available else None
            if mts is not None and "error" in mts.info:
                report(f"Mitsuba failed: {mts.info['error']}")
                mts.close()
                mts = None
            zref = np.load(mts.info["reference"]) if mts is not None else None
            if mts is not None and scene_name == "cornell-box":  # the same scene: the references must agree
                raw = float(((zref["mean"] - ref_mean)[mask] ** 2).mean())
                noise = float((ref_var + zref["var"])[mask].mean())
                report(f"The two references differ by RMSE {raw ** 0.5:.5f}; their noise "
                       f"alone explains {noise ** 0.5:.5f} (image mean "
                       f"{ref_mean[mask].mean():.4f}).")
                report()
            for sampler in samplers:
                rf.render(1, sampler, 0)  # every sampler's branch compiled and warm
            # Interleaved: each repeat renders Mitsuba, then every sampler, so
            # that a drift of this VM's speed weighs on every row alike.
            for spp in args.spp:
                runs: dict[str, list] = {}
                for rep in range(args.repeat):
                    if mts is not None:
                        time.sleep(SETTLE)
                        runs.setdefault("mitsuba", []).append(mts.render(spp, 1 + rep))
                    for sampler in samplers:
                        time.sleep(SETTLE)
                        runs.setdefault(sampler, []).append(rf.render(spp, sampler, 1 + rep))
                if mts is not None:
                    seconds = median([r["seconds"] for r in runs["mitsuba"]])
                    mse = float(np.mean([mse_against(np.load(r["image"]), zref["mean"],
                                                     zref["var"], mask) for r in runs["mitsuba"]]))
                    mts_eff[spp] = 1.0 / (mse * seconds)
                    rows.append((f"Mitsuba {mts.info['version']} {mts.info['variant']}, independent",
                                 spp, size[0] * size[1] * spp / seconds, None, mse, mts_eff[spp]))
                for sampler in samplers:
                    seconds = median([r[2] for r in runs[sampler]])
                    mse = float(np.mean([mse_against(r[0], ref_mean, ref_var, mask)
                                         for r in runs[sampler]]))
                    label = f"rayfarm, {sampler}" + (" (default)" if sampler == default else "")
                    rows.append((label, spp, size[0] * size[1] * spp / seconds,
                                 runs[sampler][0][3] / seconds / args.workers, mse,
                                 1.0 / (mse * seconds)))
                    print(f"  {label:28s} {spp:4d} spp  {rows[-1][2] / 1e6:.2f} M samples/s  "
                          f"RMSE {mse ** 0.5:.5f}", flush=True)
            if mts is not None:
                mts.close()
        report("| renderer, sampler | spp | samples/s | rays/s per core | RMSE | efficiency | vs Mitsuba |")
        report("|---|---|---|---|---|---|---|")
        for label, spp, rate, rays, mse, eff in sorted(rows, key=lambda r: (r[1], r[0][0] != "M")):
            ratio = f"{eff / mts_eff[spp]:.2f}" if spp in mts_eff else "-"
            report(f"| {label} | {spp} | {rate / 1e6:.2f} M | "
                   f"{'-' if rays is None else f'{rays / 1e6:.2f} M'} | {max(mse, 0.0) ** 0.5:.5f} | "
                   f"{eff:.4g} | {ratio} |")

    if not args.no_traversal and not args.farm_only:
        import traversal
        report()
        report("## BVH traversal alone (one thread, bench/traversal.py)")
        report()
        report("Camera rays, one cosine bounce from each camera hit (closest hit) and a shadow ray "
               "from there to a sampled light point (any hit), traced on one thread. "
               f"`{traversal.HEAVY}` is cornell-box with a bumpy ball of about 100 k triangles "
               "in place of the tall box (bench/heavy_mesh.py).")
        report()
        for line in traversal.table(traversal.SIZES, repeat=3):
            report(line)

    if not args.no_farm:
        scene_name = args.scenes.split(",")[0]
        size = SIZES[scene_name]
        report()
        report(f"## Scaling and farm overhead ({scene_name}, `{default}`)")
        report()
        rf = Rayfarm(scene_name, size, args.depth, 1)
        one = size[0] * size[1] * 64 / median([rf.render(64, default, s)[2] for s in (1, 2)])
        import numba
        numba.set_num_threads(args.workers)
        many = size[0] * size[1] * 64 / median([rf.render(64, default, s)[2] for s in (1, 2)])
        pool_one = pool_rate(scene_name, size, args.depth, 64, 1, default)
        pool_many = pool_rate(scene_name, size, args.depth, 64, args.workers, default)
        report(f"Samples/s at 64 spp: Numba threads 1 -> {args.workers}: {one / 1e6:.2f} M -> "
               f"{many / 1e6:.2f} M ({many / one:.2f}x); local pool processes 1 -> {args.workers}: "
               f"{pool_one / 1e6:.2f} M -> {pool_many / 1e6:.2f} M ({pool_many / pool_one:.2f}x).")
        report()
        # spp for jobs of about 10 s and 1 s of kernel time on all cores
        spp_for = {target: max(1, int(round(target * many / (size[0] * size[1]))))
                   for target in (10.0, 1.0)}
        kernel = {spp: median([rf.render(spp, default, s)[2] for s in (1, 2, 3)])
                  for spp in spp_for.values()}
        farm = farm_times(scene_name, size, args.depth, list(spp_for.values()), args.workers,
                          default)
        report(f"Seconds of one image, medians: *kernel* (of 3), one unit in-process on "
               f"{args.workers} Numba threads; *pool*, `renderer.render` on a local pool of "
               f"{args.workers} processes (the job's plan of 64-pixel tiles, each a unit, "
               f"merged), no service; *service*, submit-to-done through `rayfarm serve` "
               f"(embedded executor, SQLite, {args.workers} render processes), with the "
               f"service process's CPU seconds (on {os.cpu_count()} cores, CPU the service "
               f"uses is CPU a render process waits for); pool and service runs alternate, "
               f"{PAIRS} pairs. *Service's share* = the median over the pairs of "
               f"service / pool - 1; *farm* = service / kernel - 1.")
        report()
        report("| job | plan | kernel | pool | service | service CPU | service's share | farm |")
        report("|---|---|---|---|---|---|---|---|")
        for target, spp in spp_for.items():
            k = kernel[spp]
            for plan, progressive in (("one pass", False), ("progressive", True)):
                alone, wall, cpu, share = farm[spp][progressive]
                report(f"| {spp} spp (~{target:g} s) | {plan} | {k:.2f} s | {alone:.2f} s | "
                       f"{wall:.2f} s | {cpu:.2f} s | {100 * share:+.1f} % | "
                       f"{100 * (wall / k - 1):+.1f} % |")
    report()
    report(NOTES)
    if args.out:
        Path(args.out).write_text("\n".join(report.lines) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
