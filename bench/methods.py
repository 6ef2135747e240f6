"""Every rendering method on `cornell-box` and `veach-mis`, at equal spp and at equal time.

    python bench/methods.py                        # 16 spp and 4 s per image, depth 5
    python bench/methods.py --spp 64 --seconds 10 --reference-spp 2048

For each scene it first renders a long `path-mis` reference, then every
registered method at equal samples per pixel and at (about) equal wall time,
through the local process pool (`renderer.render`, the farm's plan -> units
-> merge path). It prints a table per scene:

    method, spp, seconds, camera samples/s, RMSE against the reference

and writes `docs/methods.md` (the tables) and `docs/methods.png` (a labelled
grid: one row per scene, one column per method, the equal-time renders).
RMSE is over all pixels and channels of the linear radiance, so a biased
method (raster, direct) keeps its bias however long it runs.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("cornell-box", "veach-mis")


def rmse(image: np.ndarray, reference: np.ndarray) -> float:
    return float(np.sqrt(np.mean((image - reference) ** 2)))


def run(pool, scene, method, spp, depth, seed):
    from renderer import RenderSpec, render, resolve_document

    cam = resolve_document(scene)["camera"]
    spec = RenderSpec(method=method, spp=spp, depth=depth, width=cam["width"],
                      height=cam["height"], tile_size=32, seed=seed)
    t0 = time.perf_counter()
    film = render(scene, spec, pool=pool)
    return film.mean(), time.perf_counter() - t0, film.stats["samples"]


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--spp", type=int, default=16, help="equal-spp runs")
    parser.add_argument("--seconds", type=float, default=4.0, help="equal-time budget per image")
    parser.add_argument("--depth", type=int, default=5)
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    args = parser.parse_args(argv)

    from renderer import METHODS, LocalPool

    methods = list(dict.fromkeys(m.name for m in METHODS.values()))
    lines = [f"# Methods compared (`python bench/methods.py --spp {args.spp} --seconds "
             f"{args.seconds} --depth {args.depth} --reference-spp {args.reference_spp}`)", ""]
    grid_rows = []
    with LocalPool(args.workers) as pool:
        for scene in SCENES:
            reference, ref_seconds, _ = run(pool, scene, "path-mis", args.reference_spp,
                                            args.depth, seed=12345)
            print(f"\n{scene}: reference path-mis {args.reference_spp} spp in {ref_seconds:.1f} s")
            header = f"{'method':<16}{'budget':<12}{'spp':>7}{'seconds':>10}{'samples/s':>14}{'RMSE':>12}"
            print(header)
            lines += [f"## {scene}", "",
                      f"Reference: `path-mis`, {args.reference_spp} spp, depth {args.depth}.", "",
                      "| method | budget | spp | seconds | samples/s | RMSE |", "|---|---|---|---|---|---|"]
            row = [("reference", reference)]
            for method in methods:
                image, seconds, samples = run(pool, scene, method, args.spp, args.depth, seed=1)
                rate = samples / seconds
                results = [("equal spp", args.spp, seconds, rate, rmse(image, reference))]
                pixels = samples / args.spp
                spp_t = max(1, int(args.seconds * rate / pixels))
                image_t, seconds_t, samples_t = run(pool, scene, method, spp_t, args.depth, seed=2)
                results.append(("equal time", spp_t, seconds_t, samples_t / seconds_t,
                                 rmse(image_t, reference)))
                row.append((f"{method} {spp_t}spp", image_t))
                for budget, spp, sec, r, err in results:
                    print(f"{method:<16}{budget:<12}{spp:>7}{sec:>10.2f}{r:>14,.0f}{err:>12.5f}")
                    lines.append(f"| {method} | {budget} | {spp} | {sec:.2f} | {r:,.0f} | {err:.5f} |")
            lines.append("")
            grid_rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "methods.md").write_text("\n".join(lines) + "\n")
    labelled_grid(grid_rows, args.out / "methods.png")
    print(f"\nwrote {args.out / 'methods.md'} and {args.out / 'methods.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
