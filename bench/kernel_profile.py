"""Where a render's time goes, per compiled Numba function (a sampling profile).

    python bench/kernel_profile.py                          # cornell-box, path-mis, 64 spp, sobol
    python bench/kernel_profile.py --scene veach-mis --sampler random --hot 20

Numba's machine code has no symbols a profiler can see: `perf report` shows
the samples that land in it as unknown addresses. This script runs a render
under `perf record -e cpu-clock` (a software clock, so it works in VMs that
expose no hardware counters) and names those addresses itself: the child
process compiles the kernels into an empty Numba cache (a cached kernel's
object code is handed to LLVM's loader and not kept, so its symbols could
not be listed), renders once to warm up, renders --repeat more times, then
writes every compiled function's address and size (its object code's ELF
symbols, resolved through Numba's own loader) and a copy of the executable
memory the code lives in. The parent counts each sample against those
ranges and prints every function's share of the samples taken in the
renders. With --hot N it also prints the N hottest instructions of the
hottest function (or of the hottest one whose name contains --function),
with objdump's disassembly of the dumped code (sampling
skid puts a sample on the instruction after the one that stalled).

Compiling takes one to two minutes; the renders are one thread, so the
shares are those of one core's work. Needs `perf` (Debian's linux-perf),
`readelf` and `objdump` (binutils).

Measured on 2026-11-28 (AMD EPYC Zen 4, cornell-box 128x128, 64 spp,
`sobol`): the path tracer's kernel (`_render_tile`'s parfor body: the
shading of the lanes, the sampler's inline draws, the lane bookkeeping)
49 %, `packet_intersect` 41 % (closest hit 26.5 %, shadow rays 14.7 %),
`concentric_disk` 4.9 %, the `sobol` sampler's out-of-line code 4.5 %.
In the kernel, a third of the instructions read or write the stack: the
loop keeps more values live than the registers hold.

Tried and not kept (2026-11-29, AMD EPYC Zen 5): source lines for the
samples, from line tables compiled in with NUMBA_DEBUGINFO=1 and read with
addr2line. The flag also turns on bounds checks and keeps variables alive
to the end of their scope (Numba's option defaults); with both turned back
off, the build still did not inline the kernels' helpers (cosine_hemisphere,
concentric_disk, reverse_bits32 and a dozen more showed up as functions of
their own) and a render took 60 % longer (0.84 s against 0.52 s). Lines
inlined at Numba's IR level (`kernel_inline`) also all carry the kernel's
own file name. A line profile of that build does not describe the release
build, so this script reads instructions only.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import ctypes
import gc
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def child(args) -> None:
    """Render under the parent's perf; write the symbols, the code and the
    time window of the measured renders into args.out."""
    import numba

    numba.set_num_threads(1)
    from renderer import RenderSpec, Unit, load_scene, run_unit

    scene = load_scene(args.scene)
    spec = RenderSpec(method=args.method, spp=args.spp, depth=args.depth, width=args.size,
                      height=args.size, tile_size=args.size, seed=3,
                      sampler=args.sampler).validate()
    whole = Unit(0, 0, 0, args.size, args.size, 0, args.spp)
    run_unit(scene, spec, whole)  # compiles
    out = Path(args.out)
    start = time.clock_gettime(time.CLOCK_MONOTONIC)
    t0 = time.perf_counter()
    for _ in range(args.repeat):
        run_unit(scene, spec, whole)
    seconds = time.perf_counter() - t0
    end = time.clock_gettime(time.CLOCK_MONOTONIC)
    symbols = {}
    from numba.core.registry import CPUDispatcher
    for obj in gc.get_objects():
        if not isinstance(obj, CPUDispatcher):
            continue
        for cres in obj.overloads.values():
            library = cres.library
            try:
                _, _, (elf, _) = library.serialize_using_object_code()
            except (RuntimeError, ValueError):
                continue  # loaded from a cache: no object code kept
            with tempfile.NamedTemporaryFile(suffix=".o") as f:
                f.write(elf)
                f.flush()
                table = subprocess.run(["readelf", "-sW", f.name], capture_output=True,
                                       text=True, check=True).stdout
            for line in table.splitlines():
                cols = line.split()
                if len(cols) >= 8 and cols[3] == "FUNC" and cols[6] != "UND":
                    address = library.get_pointer_to_function(cols[7])
                    if address:
                        symbols[address] = (int(cols[2]), cols[7])
    regions = []
    with open("/proc/self/maps") as maps:
        for line in maps:
            cols = line.split()
            if "x" in cols[1] and len(cols) < 6:  # anonymous executable memory: JIT code
                lo, hi = (int(v, 16) for v in cols[0].split("-"))
                (out / f"{lo:x}.bin").write_bytes(ctypes.string_at(lo, hi - lo))
                regions.append((lo, hi))
    (out / "child.json").write_text(json.dumps({
        "symbols": [[a, s, n] for a, (s, n) in sorted(symbols.items())],
        "regions": regions, "window": [start, end], "seconds": seconds}))


def short_name(mangled: str) -> str:
    """A readable name from Numba's mangled one: the dotted path before the hash."""
    name = mangled.removeprefix("cpython.").removeprefix("cfunc.")
    if "parfor_gufunc" in name:
        return ("__gufunc__ " if name.startswith("__gufunc__") else "") + "parfor body"
    if name.startswith("_ZN"):
        parts, rest = [], name[3:]
        while rest and rest[0].isdigit():
            digits = len(rest) - len(rest.lstrip("0123456789"))
            n = int(rest[:digits])
            parts.append(rest[digits:digits + n])
            rest = rest[digits + n:]
        # a specialization on a literal argument (packet_intersect's any_hit)
        literals = re.findall(r"Literal_5b\w+?_5d_28(\w+?)_29", rest)
        return ".".join(parts) + (f" ({', '.join(literals)})" if literals else "")
    return name[:60]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="cornell-box")
    parser.add_argument("--method", default="path-mis")
    parser.add_argument("--sampler", default="sobol")
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--size", type=int, default=128, help="image width and height")
    parser.add_argument("--repeat", type=int, default=3, help="measured renders")
    parser.add_argument("--hot", type=int, default=0,
                        help="also print the hottest instructions of the hottest function")
    parser.add_argument("--function", default="",
                        help="with --hot: the hottest function whose name contains this "
                             "(e.g. 'intersect (True)' for the shadow rays' packets)")
    parser.add_argument("--out", default=None, help=argparse.SUPPRESS)  # the child's
    args = parser.parse_args(argv)
    if args.out:
        child(args)
        return 0
    missing = [tool for tool in ("perf", "readelf", "objdump") if shutil.which(tool) is None]
    if missing:
        print(f"needs {', '.join(missing)} (apt-get install linux-perf binutils)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        env = dict(os.environ, NUMBA_CACHE_DIR=str(work / "numba-cache"), NUMBA_NUM_THREADS="1")
        command = [sys.executable, __file__, "--out", str(work), "--scene", args.scene,
                   "--method", args.method, "--sampler", args.sampler, "--spp", str(args.spp),
                   "--depth", str(args.depth), "--size", str(args.size),
                   "--repeat", str(args.repeat)]
        print("compiling and rendering under perf (about two minutes) ...", flush=True)
        record = subprocess.run(["perf", "record", "-q", "-k", "monotonic", "-e", "cpu-clock",
                                 "-F", "2000", "-o", str(work / "perf.data"), "--", *command],
                                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True)
        if record.returncode != 0 or not (work / "child.json").exists():
            # perf refused (kernel.perf_event_paranoid, a container) or the render failed
            print(f"perf record failed ({record.returncode}):\n{record.stderr[-2000:]}",
                  file=sys.stderr)
            return 1
        info = json.loads((work / "child.json").read_text())
        script = subprocess.run(["perf", "script", "-i", str(work / "perf.data"), "-F",
                                 "time,ip"], capture_output=True, text=True, check=True).stdout
        lo_t, hi_t = info["window"]
        starts = [a for a, _, _ in info["symbols"]]
        counts: collections.Counter = collections.Counter()
        by_ip: collections.Counter = collections.Counter()
        total = 0
        for line in script.splitlines():
            cols = line.split()
            if len(cols) < 2:
                continue
            when, ip = float(cols[0].rstrip(":")), int(cols[1], 16)
            if not lo_t <= when <= hi_t:
                continue  # compiling, warming up, exiting
            total += 1
            i = bisect.bisect_right(starts, ip) - 1
            if i >= 0 and ip < starts[i] + max(info["symbols"][i][1], 1):
                counts[i] += 1
                by_ip[ip] += 1
            else:
                counts[-1] += 1
        print(f"\n{args.scene} {args.size}x{args.size}, {args.method}, {args.spp} spp, "
              f"{args.sampler}, one thread: {args.repeat} renders in {info['seconds']:.2f} s, "
              f"{total} samples\n")
        print("| share | function |\n|---|---|")
        for i, n in counts.most_common():
            name = "outside Numba's code (Python, NumPy, the kernel)" if i < 0 else \
                short_name(info["symbols"][i][2])
            print(f"| {100 * n / max(total, 1):5.1f} % | {name} |")
        if args.hot and counts:
            top = next((i for i, _ in counts.most_common() if i >= 0
                        and args.function in short_name(info["symbols"][i][2])), None)
            if top is None:
                print(f"\nno function named like {args.function!r} took samples")
                return 0
            address, size, _ = info["symbols"][top]
            region = next((lo, hi) for lo, hi in info["regions"] if lo <= address < hi)
            asm = subprocess.run(["objdump", "-D", "-b", "binary", "-mi386:x86-64",
                                  f"--adjust-vma={region[0]:#x}",
                                  str(work / f"{region[0]:x}.bin")],
                                 capture_output=True, text=True, check=True).stdout
            lines = {}
            for line in asm.splitlines():
                head, _, rest = line.partition(":")
                try:
                    lines[int(head.strip(), 16)] = rest.split("\t")[-1].strip()
                except ValueError:
                    continue
            print(f"\nhottest instructions of {short_name(info['symbols'][top][2])} "
                  "(offset, samples, instruction):")
            hot = [(ip, n) for ip, n in by_ip.items() if address <= ip < address + size]
            for ip, n in sorted(hot, key=lambda kv: -kv[1])[:args.hot]:
                print(f"  {ip - address:#7x} {n:5d}  {lines.get(ip, '?')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
