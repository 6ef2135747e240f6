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

Part 2, the lecture's chart measured (on `cornell-box`, small), by the
estimator lab (`POST /experiments` on an embedded farm started here, so
this script and the dashboard's Lab page measure with one implementation,
renderer.lab): every method (and the CHART_VARIANTS) at the spp levels
`--chart-spp` x 1, 4, 16, 64, `--chart-runs` independent renders each,
against a `path-mis` reference of `--chart-reference-spp`. Per level: the
pixel blocks whose t test of the repeats' average against the reference is
significant, and the binomial p of that many ("biased" below 0.001); the
RMSE at each level and its log-log slope; "consistent": no bias found, or a
bias^2 that still falls at the last step. See renderer/lab.py.

Writes `docs/methods.md` (every table) and `docs/methods.png` (one row per
scene: the reference and every method's equal-time render).
"""

from __future__ import annotations

import argparse
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


def chart(args, methods, lines) -> None:
    """Part 2: the estimator lab's experiment (module doc), through the API of
    an embedded farm in a temporary data directory."""
    import tempfile

    from fastapi.testclient import TestClient

    from service.main import create_app
    from service.settings import Settings

    scene = "cornell-box"
    token = "bench-" + "0" * 40
    configs = [{"method": m} for m in methods]
    configs += [{"method": m, "options": opts, "label": label}
                for label, (m, opts) in CHART_VARIANTS.items() if m in methods]
    cam_spec = spec_for(scene, "path-mis", 1, args.depth, 0, args.chart_size)
    body = {"scene": scene, "width": cam_spec.width, "height": cam_spec.height,
            "depth": args.depth, "repeats": args.chart_runs, "block": args.chart_block,
            "spp": [args.chart_spp * k for k in CHART_SPPS], "configs": configs,
            "reference": {"method": "path-mis", "spp": args.chart_reference_spp}}
    with tempfile.TemporaryDirectory() as data:
        settings = Settings(data_dir=Path(data), broker_url="", database_url="",
                            local_workers=args.workers, admin_token=token)
        with TestClient(create_app(settings), headers={"Authorization": f"Bearer {token}"}) as api:
            response = api.post("/experiments", json=body)
            if response.status_code != 201:
                raise SystemExit(f"the experiment was refused: {response.text}")
            experiment = response.json()
            t0 = time.perf_counter()
            while experiment["status"] == "running":
                time.sleep(1.0)
                experiment = api.get(f"/experiments/{experiment['id']}").json()
            if experiment["status"] != "done":
                raise SystemExit(f"the experiment {experiment['status']}: {experiment['error']}")
            for name in ("plot", "maps"):
                (args.out / f"methods-lab-{name}.png").write_bytes(
                    api.get(experiment[f"{name}_url"]).content)
    print(f"\nchart: {len(configs)} configurations x {len(CHART_SPPS)} levels x "
          f"{args.chart_runs} repeats in {time.perf_counter() - t0:.0f} s")
    lines += ["## Bias and consistency, measured (the lecture's chart)", "",
              f"The estimator lab (`POST /experiments`, renderer/lab.py) on `{scene}` at "
              f"{body['width']}x{body['height']}, depth {args.depth}; reference `path-mis` "
              f"{args.chart_reference_spp} spp; {args.chart_runs} repeats per level. Bias: "
              f"{args.chart_block}x{args.chart_block}-pixel blocks (luminance) whose t test is "
              "significant at 5 %, and the binomial p of that many (biased below 0.001). "
              "Figures: `methods-lab-plot.png`, `methods-lab-maps.png`.", "",
              "| method | significant blocks at " + " / ".join(f"{s}x" for s in CHART_SPPS)
              + " | mean bias (last) | no bias found? | RMSE at "
              + " / ".join(f"{s}x" for s in CHART_SPPS) + " | slope | consistent? |",
              "|---|---|---|---|---|---|---|"]
    print(f"{'method':<26}{'blocks':>20}{'bias':>9}{'unbiased':>10}{'slope':>8}{'consistent':>12}")
    for config in experiment["report"]:
        levels = config["levels"]
        blocks = " / ".join(f"{lv['biased_blocks']}/{lv['blocks']}" for lv in levels)
        rmse = " / ".join(f"{lv['rmse']:.4f}" for lv in levels)
        verdict = "yes" if config["unbiased"] else "no"
        consistent = {True: "yes", False: "no", None: "?"}[config["consistent"]]
        print(f"{config['label']:<26}{blocks:>20}{100 * levels[-1]['relative_bias']:>8.2f}%"
              f"{verdict:>10}{config['slope']:>8.2f}{consistent:>12}")
        lines.append(f"| {config['label']} | {blocks} | {100 * levels[-1]['relative_bias']:.2f} % | "
                     f"{verdict} | {rmse} | {config['slope']:.2f} | {consistent} |")
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
    parser.add_argument("--chart-runs", type=int, default=8)
    parser.add_argument("--chart-block", type=int, default=8, help="pixels per block side")
    parser.add_argument("--chart-reference-spp", type=int, default=16384)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    args = parser.parse_args(argv)

    from renderer import METHODS, LocalPool

    methods = args.methods or list(dict.fromkeys(m.name for m in METHODS.values()))
    if args.chart_runs < 2:
        parser.error("--chart-runs must be at least 2 (the bias test needs the spread over them)")
    shown = sys.argv[1:] if argv is None else argv
    command = " ".join(["python bench/methods.py", *shown])
    lines = [f"# Methods compared (`{command}`, {time.strftime('%Y-%m-%d')}, "
             f"{args.workers} worker processes)", "",
             "Equal spp and equal time per scene, then the bias and consistency of every "
             "method measured; see `bench/methods.py` for how.", ""]
    grid_rows: list = []
    args.out.mkdir(parents=True, exist_ok=True)
    with LocalPool(args.workers) as pool:
        compare(pool, args, methods, lines, grid_rows)
    if not args.skip_chart:
        chart(args, methods, lines)
    (args.out / "methods.md").write_text("\n".join(lines) + "\n")
    if grid_rows:
        labelled_grid(grid_rows, args.out / "methods.png")
    print(f"\nwrote {args.out / 'methods.md'} and {args.out / 'methods.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
