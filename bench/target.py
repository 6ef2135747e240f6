"""What rendering to a noise target saves: the samples an adaptive render to a
target spends against a fixed-spp render that reaches the same error.

    python bench/target.py                       # cornell-box and veach-mis, writes docs/target.md
    python bench/target.py --scenes veach-mis --targets 0.2 --out ''

For each scene, `path-mis` with the default sampler, depth 7: a render to each
target (renderer/target.py: tiles of 16 pixels stop receiving passes when
their own error statistic meets the target) on a local pool, and fixed-spp
renders up a ladder of spp. The statistic is `film.image_error`, the 95th
percentile over the pixels brighter than 1 % of the image mean of the
relative standard error from the var channels. *Equal-statistic spp*: the
spp at which the fixed renders' statistic meets the target (log-log
interpolation between the rungs around it); *saved* is the samples of that
fixed render over the adaptive render's. The true error is measured too: RMSE
over the pixels that do not see an emitter against bench/throughput.py's
reference, and the spp at which the fixed renders reach the adaptive
render's RMSE.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from denoise import equal_rmse_spp, render_film, rmse  # noqa: E402
from throughput import SIZES, Rayfarm, emitter_mask, rayfarm_reference  # noqa: E402

READING = """## Reading the tables

- The adaptive render equalises the statistic over tiles: a tile whose
  pixels are bright and smooth stops early, a dark or caustic-lit one goes
  on. The fixed render must take every pixel to the spp the worst 5 % of
  pixels need; what it spends on the rest is what the target saves.
- RMSE weighs a pixel by its radiance, the statistic by its relative error:
  the adaptive render puts its samples where the relative error is high (the
  dark corners), so at equal samples its RMSE is not lower than a fixed
  render's. Render to a target when the question is "is every part of the
  image clean enough", not "is the bright part right".
- veach-mis's linear RMSE is decided by the few pixels where the smooth
  plates reflect the two smallest lights (radiance 338 and 3040; see
  docs/denoise.md): the fixed renders' RMSE falls in jumps as those pixels
  happen to converge (1.9 at 16 spp, 0.30 at 64, 0.28 at 128, 0.12 at 512,
  0.016 at 2048), so its equal-RMSE columns mean little. A relative-error
  target lets a tile of bright highlights stop once its relative error is
  low, which leaves their absolute error, and so the RMSE, large.
- The statistic reads the var channels, which for the default (stratified)
  sampler overstate the error (README, "Pixel samplers"): a target of 10 %
  stops when the true error is lower still.
- Each decision judges a tile by the pixels the frame's statistic counts
  (brighter than 1 % of the frame's mean). Judging a tile by its own mean
  instead made veach-mis's adaptive render dearer than a fixed one (0.52x
  at 25 %, 0.84x at 15 %): dark tiles kept refining pixels the frame's
  statistic ignores.
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="cornell-box,veach-mis")
    parser.add_argument("--targets", default="0.25,0.15,0.1",
                        type=lambda s: [float(v) for v in s.split(",")])
    parser.add_argument("--ladder", default="16,32,64,128,256,512,1024,2048,4096",
                        type=lambda s: [int(v) for v in s.split(",")])
    parser.add_argument("--max-spp", type=int, default=4096)
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--ref-spp", type=int, default=8192)
    parser.add_argument("--refs", default=str(Path.home() / ".cache" / "rayfarm-bench"))
    parser.add_argument("--out", default=str(ROOT / "docs" / "target.md"))
    args = parser.parse_args(argv)
    Path(args.refs).mkdir(parents=True, exist_ok=True)

    from renderer import LocalPool, RenderSpec
    from renderer.target import Target, render_to_target

    lines = ["# Rendering to a noise target: samples saved", "",
             f"`python bench/target.py`, {time.strftime('%Y-%m-%d')}: `path-mis`, depth "
             f"{args.depth}, the default sampler, tiles of {args.tile_size} pixels, "
             f"{args.workers} render processes. *Statistic*: film.image_error (95th percentile "
             f"of the pixels' relative standard error). Fixed renders at "
             f"{', '.join(map(str, args.ladder))} spp; *equal-statistic spp* and *equal-RMSE "
             f"spp* interpolate them log-log; *saved*: the fixed render's samples over the "
             f"adaptive one's. RMSE over the pixels that do not see an emitter, against the "
             f"{args.ref_spp}-spp reference of bench/throughput.py.", ""]
    with LocalPool(args.workers) as pool:
        for scene_name in args.scenes.split(","):
            rf = Rayfarm(scene_name, SIZES[scene_name], args.depth, args.workers)
            mask = emitter_mask(rf)
            ref_mean, ref_var = rayfarm_reference(rf, args.ref_spp, Path(args.refs))
            stat_ladder, rmse_ladder = [], []
            for spp in args.ladder:
                film, seconds = render_film(rf, spp, seed=11)
                stat_ladder.append((spp, film.image_error()))
                rmse_ladder.append((spp, rmse(film.mean(), ref_mean, ref_var, mask)))
                print(f"{scene_name} fixed {spp} spp: statistic {stat_ladder[-1][1]:.4f}, "
                      f"RMSE {rmse_ladder[-1][1]:.5f} ({seconds:.1f} s)", flush=True)
            pixels = rf.width * rf.height
            lines += [f"## {scene_name}, {rf.width}x{rf.height}", "",
                      "| target | stopped | passes | units run / skipped | mean spp | seconds "
                      "| statistic | equal-statistic spp | saved | RMSE | equal-RMSE spp "
                      "| saved (RMSE) |",
                      "|---|---|---|---|---|---|---|---|---|---|---|---|"]
            for rel in args.targets:
                spec = RenderSpec(method="path-mis", depth=args.depth, width=rf.width,
                                  height=rf.height, tile_size=args.tile_size, seed=1)
                t0 = time.perf_counter()
                film, report = render_to_target(scene_name, spec, Target(rel, args.max_spp),
                                                pool=pool)
                seconds = time.perf_counter() - t0
                mean_spp = float(film.weight.sum()) / pixels
                err = rmse(film.mean(), ref_mean, ref_var, mask)
                equal_stat = equal_rmse_spp(stat_ladder, film.image_error())
                equal_err = equal_rmse_spp(rmse_ladder, err)

                def saved(equal, ladder):
                    if any(b[1] >= a[1] for a, b in zip(ladder, ladder[1:])):
                        return "n/a | n/a"  # the fixed renders' curve does not fall: no inverse
                    return (f"{equal:.0f} | {equal / mean_spp:.2f}x" if equal else
                            f"> {args.ladder[-1]} | > {args.ladder[-1] / mean_spp:.1f}x")

                lines.append(f"| {100 * rel:g} % | {report.stopped} | {report.passes} | "
                             f"{report.units_run} / {report.units_skipped} | {mean_spp:.0f} | "
                             f"{seconds:.1f} | {100 * film.image_error():.2f} % | "
                             f"{saved(equal_stat, stat_ladder)} | {err:.5f} | "
                             f"{saved(equal_err, rmse_ladder)} |")
                print(lines[-1], flush=True)
            lines.append("")
    lines.append(READING)
    if args.out:
        Path(args.out).write_text("\n".join(lines))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
