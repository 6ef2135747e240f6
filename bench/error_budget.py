"""Where a render's error comes from: its MSE split by path depth.

    python bench/error_budget.py                                  # cornell-box, sobol and random, 64 spp
    python bench/error_budget.py --scene veach-mis --spp 256 --samplers sobol
    python bench/error_budget.py --samplers sobol --roulette 1   # pbrt-v4's and Mitsuba's roulette

The MSE of an unbiased image is its variance, measured here as the spread of
--repeat renders with different seeds (per pixel, averaged over the pixels
that do not see an emitter, as bench/throughput.py does). Rendered at
depth 1 (direct light), 2, 3 and --depth, the differences say how much of
the error each band of bounces adds (the bands are not independent, so a
share can come out slightly negative; the total is exact). It tells which
lever can pay: a sampler that stratifies the first bounces cannot remove
error that lives in the deep ones, and Russian roulette trades deep-bounce
error against time.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

SIZES = {"cornell-box": (256, 256), "veach-mis": (256, 144)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="cornell-box", choices=sorted(SIZES))
    parser.add_argument("--samplers", default="sobol,random")
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--repeat", type=int, default=6, help="seeds per depth")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--roulette", type=float, default=None,
                        help="path-mis's Russian roulette survival scale (default: the method's)")
    args = parser.parse_args(argv)
    options = {} if args.roulette is None else {"roulette": args.roulette}

    import numba

    from renderer import RenderSpec, Unit, load_scene, merge, run_unit

    numba.set_num_threads(args.workers)
    width, height = SIZES[args.scene]
    scene = load_scene(args.scene)

    def render(spp: int, sampler: str, seed: int, depth: int):
        spec = RenderSpec(method="path-mis", spp=spp, depth=depth, width=width, height=height,
                          tile_size=max(width, height), seed=seed, sampler=sampler,
                          options=options).validate()
        t0 = time.perf_counter()
        part = run_unit(scene, spec, Unit(0, 0, 0, width, height, 0, spp))
        return merge(width, height, [part]).mean(), time.perf_counter() - t0

    mask = render(4, "random", 1, 0)[0].max(axis=2) <= 0.0  # pixels that see no emitter
    depths = sorted({1, 2, 3, args.depth})
    print(f"{args.scene} {width}x{height}, path-mis {options or ''}, {args.spp} spp, "
          f"{args.repeat} seeds per row; "
          "MSE = variance over seeds, mean over the pixels that see no emitter")
    print(f"{'sampler':8s} {'depth':>5s} {'MSE':>10s} {'added':>10s} {'share':>6s} {'s/render':>8s}")
    for sampler in args.samplers.split(","):
        render(1, sampler, 1, args.depth)  # compile outside the timing
        rows = []
        for depth in depths:
            runs = [render(args.spp, sampler, 1000 + r, depth) for r in range(args.repeat)]
            images = np.stack([image for image, _ in runs])
            mse = float(images.var(axis=0, ddof=1)[mask].mean())
            rows.append((depth, mse, float(np.median([s for _, s in runs]))))
        total, before = rows[-1][1], 0.0
        for depth, mse, seconds in rows:
            print(f"{sampler:8s} {depth:5d} {mse:10.3e} {mse - before:10.3e} "
                  f"{(mse - before) / total:6.0%} {seconds:8.2f}")
            before = mse
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
