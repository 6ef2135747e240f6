"""Every rendering method compared: equal spp, equal time, bias and consistency.

    python bench/methods.py                       # the defaults below, ~15 minutes on 2 cores
    python bench/methods.py --scenes cornell-box --seconds 2 --skip-chart

Part 1, per scene (`cornell-box`, `veach-mis`, `cornell-caustic`,
`door-ajar`): a long reference (`path-mis`; `bdpt` on the caustic and door
scenes, see REFERENCE), then every registered method at
equal samples per pixel and at (about) equal wall time, through the local
process pool (`renderer.render`: the farm's plan -> units -> merge path).
The table gives spp, seconds, samples/s and the RMSE against the reference.
"spp" means what each method makes of it: camera samples per pixel for the
tile methods and BDPT, light paths per pixel for `light`, mutations per
pixel for `mlt`, iterations for `photon`, display samples for `radiosity`.

Part 2, the lecture's chart measured (on `cornell-box`, small):
- bias: R independent renders (different seeds) at low spp are averaged;
  per block of pixels (block means are near-normal where single pixels at
  low spp are far too skewed for a t statistic) and channel,
  z = (average - reference) / sqrt(spread^2 / R + reference variance).
  For an unbiased method z^2 averages nu/(nu - 2) over the blocks (a t statistic with nu = R - 1 degrees of freedom); a systematic error of
  the method (blur, missing light, meshing) makes it grow. The verdict
  "unbiased" is mean z^2 within 4 standard errors of that value.
- consistency: RMSE against the reference at spp = 1, 4, 16, 64 (x the
  method's base spp): the log-log slope. A consistent method's error keeps
  falling (slope near -1/2 for plain Monte Carlo); an inconsistent one
  levels off at its bias (slope near 0 at the end). The verdict
  "consistent" asks for the last step's slope below -0.25.
The reference for part 2 is `path-mis` at `--chart-reference-spp`, whose own
variance is in the z denominator.

Writes `docs/methods.md` (every table) and `docs/methods.png` (one row per
scene: the reference and every method's equal-time render).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("cornell-box", "veach-mis", "cornell-caustic", "door-ajar")
# The reference of each scene: an unbiased method that converges there, with
# its spp as a fraction of --reference-spp. Path tracing finds the caustics
# seen directly (light -> glass -> floor -> camera) and the light behind the
# door only by rare BSDF samples; BDPT's light subpaths find both.
REFERENCE = {"cornell-caustic": ("bdpt", 0.5), "door-ajar": ("bdpt", 0.5)}
CHART_SPPS = (1, 4, 16, 64)
# Extra rows of the chart: the same method with a parameter that makes its
# systematic error larger than the noise this small experiment can resolve
# (with the defaults, SPPM's bias on cornell-box and radiosity's meshing bias
# of about 0.5 % hide under the noise of 16 renders of 8 spp).
CHART_VARIANTS = {"photon radius=0.15": ("photon", {"radius": 0.15}),
                  "radiosity patch_size=0.5": ("radiosity", {"patch_size": 0.5})}


def rmse(image: np.ndarray, reference: np.ndarray) -> float:
    return float(np.sqrt(np.mean((image - reference) ** 2)))


def spec_for(scene: str, method: str, spp: int, depth: int, seed: int, size: int,
             options: dict | None = None):
    from renderer import RenderSpec, resolve_document

    cam = resolve_document(scene)["camera"]
    width = size
    height = max(1, round(size * cam["height"] / cam["width"]))
    # `random`, not the default `sobol`: the estimators are compared with
    # independent samples, so the reference's var channel is its variance
    # (the z of part 2) and plain Monte Carlo's error falls as spp^-1/2 (the
    # slopes), as when docs/methods.md was measured
    return RenderSpec(method=method, spp=spp, depth=depth, width=width, height=height,
                      tile_size=32, seed=seed, sampler="random", options=options or {})


def run(pool, scene, spec):
    from renderer import render

    t0 = time.perf_counter()
    film = render(scene, spec, pool=pool)
    return film, time.perf_counter() - t0


def labelled_grid(rows: list[list[tuple[str, np.ndarray]]], path: Path) -> None:
    from PIL import Image, ImageDraw

    from renderer.film import tonemap_srgb8

    label_h = 14
    tiles = [[(label, Image.fromarray(tonemap_srgb8(img))) for label, img in row] for row in rows]
    width = max(sum(t.width for _, t in row) for row in tiles)
    height = sum(max(t.height for _, t in row) + label_h for row in tiles)
    grid = Image.new("RGB", (width, height), (24, 24, 24))
    draw = ImageDraw.Draw(grid)
    y = 0
    for row in tiles:
        x = 0
        row_h = max(t.height for _, t in row)
        for label, tile in row:
            draw.text((x + 3, y + 1), label, fill=(230, 230, 230))
            grid.paste(tile, (x, y + label_h))
            x += tile.width
        y += row_h + label_h
    path.parent.mkdir(parents=True, exist_ok=True)
    grid.save(path)


def compare(pool, args, methods, lines, grid_rows) -> None:
    """Part 1: equal spp and equal time on each scene."""
    for scene in args.scenes:
        ref_method, fraction = REFERENCE.get(scene, ("path-mis", 1.0))
        ref_spp = max(1, int(args.reference_spp * fraction))
        ref_spec = spec_for(scene, ref_method, ref_spp, args.depth, 12345, args.size)
        reference_film, ref_seconds = run(pool, scene, ref_spec)
        reference = reference_film.mean()
        print(f"\n{scene}: reference {ref_method} {ref_spp} spp in {ref_seconds:.1f} s")
        print(f"{'method':<16}{'budget':<12}{'spp':>7}{'seconds':>10}{'samples/s':>14}{'RMSE':>12}")
        lines += [f"## {scene}", "",
                  f"Reference: `{ref_method}`, {ref_spp} spp ({ref_seconds:.0f} s), depth {args.depth}, "
                  f"{ref_spec.width}x{ref_spec.height}.", "",
                  "| method | budget | spp | seconds | samples/s | RMSE |", "|---|---|---|---|---|---|"]
        row = [("reference", reference)]
        for method in methods:
            film, seconds = run(pool, scene, spec_for(scene, method, args.spp, args.depth, 1,
                                                      args.size))
            samples = film.stats["samples"]
            rate = samples / seconds
            results = [("equal spp", args.spp, seconds, rate, rmse(film.mean(), reference))]
            # Time grows about linearly with spp, plus fixed costs (the pool's
            # round trips, a prepass): guess from the equal-spp run, then
            # correct once from the first guess's own time if it missed by > 20 %.
            spp_t = max(1, int(args.spp * args.seconds / seconds))
            film_t, seconds_t = run(pool, scene, spec_for(scene, method, spp_t, args.depth, 2,
                                                          args.size))
            if abs(seconds_t / args.seconds - 1.0) > 0.2:
                spp_t = max(1, int(spp_t * args.seconds / seconds_t))
                film_t, seconds_t = run(pool, scene, spec_for(scene, method, spp_t, args.depth, 2,
                                                              args.size))
            results.append(("equal time", spp_t, seconds_t, film_t.stats["samples"] / seconds_t,
                            rmse(film_t.mean(), reference)))
            row.append((f"{method} {spp_t}", film_t.mean()))
            for budget, spp, sec, r, err in results:
                print(f"{method:<16}{budget:<12}{spp:>7}{sec:>10.2f}{r:>14,.0f}{err:>12.5f}")
                lines.append(f"| {method} | {budget} | {spp} | {sec:.2f} | {r:,.0f} | {err:.5f} |")
        lines.append("")
        grid_rows.append(row)


def chart(pool, args, methods, lines) -> None:
    """Part 2: bias (z-test of the average of R renders) and consistency (slope)."""
    scene = "cornell-box"
    ref_film, ref_seconds = run(pool, scene, spec_for(scene, "path-mis", args.chart_reference_spp,
                                                      args.depth, 999, args.chart_size))
    reference, ref_var = ref_film.mean(), ref_film.variance_of_mean()
    print(f"\nchart: reference path-mis {args.chart_reference_spp} spp in {ref_seconds:.1f} s")
    runs = args.chart_runs
    nu = runs - 1
    expected = nu / (nu - 2)  # E[t^2] with nu degrees of freedom
    # Var[t^2] = 2 nu^2 (nu - 1) / ((nu - 2)^2 (nu - 4)); the pixels' mean of n of them:
    block = args.chart_block

    def block_means(image: np.ndarray) -> np.ndarray:
        """Means over block x block pixels: near-normal even at low spp, where a
        pixel's samples are too skewed for a t statistic."""
        h, w = (image.shape[0] // block) * block, (image.shape[1] // block) * block
        return image[:h, :w].reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))

    n_values = (reference.shape[0] // block) * (reference.shape[1] // block) * 3
    se = math.sqrt(2 * nu * nu * (nu - 1) / ((nu - 2) ** 2 * (nu - 4)) / n_values)
    lines += ["## Bias and consistency, measured (the lecture's chart)", "",
              f"`cornell-box` at {args.chart_size} px wide, depth {args.depth}; reference "
              f"`path-mis` {args.chart_reference_spp} spp. Bias: {runs} independent renders at "
              f"{args.chart_spp} spp averaged, z per {args.chart_block}x{args.chart_block}-pixel "
              f"block mean and channel against the reference; an unbiased "
              f"method gives mean z^2 = {expected:.3f} +- {se:.3f}. Consistency: RMSE at "
              f"spp x {', '.join(map(str, CHART_SPPS))} and its log-log slope.", "",
              "| method | mean z^2 | image mean / reference | unbiased? | RMSE at "
              + " / ".join(f"{s}x" for s in CHART_SPPS) + " | slope (all) | slope (last step) "
              "| consistent? |", "|---|---|---|---|---|---|---|---|"]
    print(f"{'method':<26}{'mean z^2':>10}{'ratio':>8}{'unbiased':>10}{'slope':>8}{'last':>8}"
          f"{'consistent':>12}")
    ref_blocks = block_means(reference)
    ref_blocks_var = block_means(np.where(np.isfinite(ref_var), ref_var, 0.0)) / args.chart_block ** 2
    rows = [(m, m, {}) for m in methods]
    rows += [(label, m, opts) for label, (m, opts) in CHART_VARIANTS.items() if m in methods]
    for label, method, options in rows:
        films = [run(pool, scene, spec_for(scene, method, args.chart_spp, args.depth, 100 + r,
                                           args.chart_size, options))[0].mean()
                 for r in range(runs)]
        stack = np.stack([block_means(f) for f in films])
        average = stack.mean(axis=0)
        spread = stack.var(axis=0, ddof=1) / runs
        denom = spread + ref_blocks_var
        with np.errstate(divide="ignore", invalid="ignore"):
            z2 = np.where(denom > 0, (average - ref_blocks) ** 2 / denom,
                          np.where(average == ref_blocks, 0.0, np.inf))
        mean_z2 = float(np.mean(np.minimum(z2, 1e6)))
        ratio = float(average.mean() / reference.mean())
        unbiased = abs(mean_z2 - expected) < 4 * se
        errors = []
        for k in CHART_SPPS:
            film, _ = run(pool, scene, spec_for(scene, method, args.chart_spp * k, args.depth, 500 + k,
                                                args.chart_size, options))
            errors.append(rmse(film.mean(), reference))
        logs = np.log(np.asarray(CHART_SPPS, float))
        slope = float(np.polyfit(logs, np.log(np.maximum(errors, 1e-12)), 1)[0])
        last = float(math.log(max(errors[-1], 1e-12) / max(errors[-2], 1e-12))
                     / math.log(CHART_SPPS[-1] / CHART_SPPS[-2]))
        consistent = last < -0.25
        print(f"{label:<26}{mean_z2:>10.3f}{ratio:>8.4f}{'yes' if unbiased else 'no':>10}"
              f"{slope:>8.2f}{last:>8.2f}{'yes' if consistent else 'no':>12}")
        lines.append(f"| {label} | {mean_z2:.3f} | {ratio:.4f} | {'yes' if unbiased else 'no'} | "
                     + " / ".join(f"{e:.4f}" for e in errors)
                     + f" | {slope:.2f} | {last:.2f} | {'yes' if consistent else 'no'} |")
    lines.append("")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--size", type=int, default=128, help="image width (height keeps the aspect)")
    parser.add_argument("--spp", type=int, default=8, help="equal-spp runs")
    parser.add_argument("--seconds", type=float, default=4.0, help="equal-time budget per image")
    parser.add_argument("--depth", type=int, default=5)
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--methods", nargs="+", default=None, help="default: every registered one")
    parser.add_argument("--skip-chart", action="store_true")
    parser.add_argument("--chart-size", type=int, default=32)
    parser.add_argument("--chart-spp", type=int, default=8)
    parser.add_argument("--chart-runs", type=int, default=16)
    parser.add_argument("--chart-block", type=int, default=8, help="pixels per block side")
    parser.add_argument("--chart-reference-spp", type=int, default=16384)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    args = parser.parse_args(argv)

    from renderer import METHODS, LocalPool

    methods = args.methods or list(dict.fromkeys(m.name for m in METHODS.values()))
    if args.chart_runs < 6:
        parser.error("--chart-runs must be at least 6 (the z^2 statistic's variance needs nu > 4)")
    shown = sys.argv[1:] if argv is None else argv
    command = " ".join(["python bench/methods.py", *shown])
    lines = [f"# Methods compared (`{command}`, {time.strftime('%Y-%m-%d')}, "
             f"{args.workers} worker processes)", "",
             "Equal spp and equal time per scene, then the bias and consistency of every "
             "method measured; see `bench/methods.py` for how.", ""]
    grid_rows: list = []
    with LocalPool(args.workers) as pool:
        compare(pool, args, methods, lines, grid_rows)
        if not args.skip_chart:
            chart(pool, args, methods, lines)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "methods.md").write_text("\n".join(lines) + "\n")
    if grid_rows:
        labelled_grid(grid_rows, args.out / "methods.png")
    print(f"\nwrote {args.out / 'methods.md'} and {args.out / 'methods.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
