"""What one denoise after the merge buys: RMSE before and after, and the spp a
raw render needs to reach the denoised error.

    python bench/denoise.py                      # cornell-box and veach-mis, writes docs/denoise.md
    python bench/denoise.py --scenes cornell-box --out ''

For each scene, `path-mis` with the default sampler at 4, 16 and 64 spp:
the raw image's RMSE and the denoised one's (renderer/denoise.py: Open Image
Denoise with the albedo and normal AOVs) against a high-spp reference, over
the pixels that do not see an emitter (as bench/throughput.py measures, whose
references it shares). Then raw renders up a ladder of spp give the raw RMSE
curve, and the spp at which it meets each denoised RMSE (log-log
interpolation between the two rungs around it) is the "equal-RMSE spp":
how many samples per pixel the denoiser saves. The denoised image is biased
(blur for noise): its RMSE says how far it is from the truth, not how it
converges.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from throughput import SIZES, Rayfarm, emitter_mask, rayfarm_reference  # noqa: E402


def render_film(rf: Rayfarm, spp: int, seed: int):
    """The merged film (with its AOVs) of one in-process render, and its seconds."""
    from renderer import RenderSpec, Unit, merge, run_unit

    spec = RenderSpec(method="path-mis", spp=spp, depth=rf.depth, width=rf.width,
                      height=rf.height, tile_size=max(rf.width, rf.height), seed=seed).validate()
    t0 = time.perf_counter()
    part = run_unit(rf.scene, spec, Unit(0, 0, 0, rf.width, rf.height, 0, spp))
    return merge(rf.width, rf.height, [part]), time.perf_counter() - t0


def rmse(image, ref_mean, ref_var, mask) -> float:
    """RMSE over `mask`, corrected for the reference's own variance."""
    return float(np.sqrt(max(((image - ref_mean)[mask] ** 2).mean() - ref_var[mask].mean(), 0.0)))


def display_rmse(image, ref_mean, mask) -> float:
    """RMSE of what a viewer sees: both images clamped to [0, 1] (the preview's
    range), over `mask`. Linear HDR error is dominated by a few highlights
    (veach-mis's plates reflect lights of radiance 338 and 3040); this is not."""
    return float(np.sqrt(((np.clip(image, 0, 1) - np.clip(ref_mean, 0, 1))[mask] ** 2).mean()))


def equal_rmse_spp(ladder: list[tuple[int, float]], target: float) -> float | None:
    """The spp at which the raw RMSE curve (spp, rmse) reaches `target`
    (log-log interpolation); None beyond the ladder's last rung."""
    for (s0, e0), (s1, e1) in zip(ladder, ladder[1:]):
        if e0 >= target >= e1:
            f = (np.log(e0) - np.log(target)) / (np.log(e0) - np.log(e1))
            return float(np.exp(np.log(s0) + f * (np.log(s1) - np.log(s0))))
    return None


READING = """## Reading the tables

- *display RMSE*: both images clamped to [0, 1] first, the range the preview
  shows. Linear RMSE weighs a pixel by its radiance, so a handful of very
  bright pixels can decide it.
- cornell-box: one denoise of the merged frame is worth 4 to 10 times the
  samples (equal-RMSE spp over spp), most at low spp, in linear and in
  display error alike.
- veach-mis: the display error falls (about 1.6 to 2.4 times), but the linear
  RMSE rises to about 3.3 whatever the spp. Its linear error lives in the few
  pixels where the smooth plates reflect the two smallest lights (radiance
  338 and 3040; see docs/throughput.md): the denoiser treats those tiny,
  extremely bright highlights as noise and spreads them out, which costs
  little on screen and a lot in linear error. There the raw image's error
  never reaches the denoised one's, so "equal-RMSE spp" says nothing (the
  ladder's first rung). For work that measures light (the estimator lab,
  references), use the raw R/G/B: they are unbiased and their var channels
  say how far to trust them; the denoised layer is for looking at.
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="cornell-box,veach-mis")
    parser.add_argument("--spp", default="4,16,64", type=lambda s: [int(v) for v in s.split(",")])
    parser.add_argument("--ladder", default="4,16,64,256,1024,4096",
                        type=lambda s: [int(v) for v in s.split(",")])
    parser.add_argument("--depth", type=int, default=7)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--ref-spp", type=int, default=8192)
    parser.add_argument("--refs", default=str(Path.home() / ".cache" / "rayfarm-bench"))
    parser.add_argument("--images", default="", help="a folder for raw/denoised PNGs to look at")
    parser.add_argument("--out", default=str(ROOT / "docs" / "denoise.md"))
    args = parser.parse_args(argv)
    Path(args.refs).mkdir(parents=True, exist_ok=True)

    from renderer.denoise import denoise_film, denoiser_version
    from renderer.film import tonemap_srgb8

    lines = ["# Denoising after the merge: error before and after", "",
             f"`python bench/denoise.py`, {time.strftime('%Y-%m-%d')}: `path-mis`, depth "
             f"{args.depth}, the default sampler, {denoiser_version()} (RT filter, quality high, "
             f"albedo and normal AOVs). RMSE over the pixels that do not see an emitter, against "
             f"the {args.ref_spp}-spp reference of bench/throughput.py, corrected for the "
             f"reference's variance. *Equal-RMSE spp*: the spp at which the raw render reaches "
             f"the denoised RMSE (raw renders at {', '.join(map(str, args.ladder))} spp, log-log "
             f"interpolation); *saved* is that over the denoised render's spp. The denoised "
             f"image is a biased post-process: its error no longer shrinks like 1/sqrt(spp).", ""]
    for scene_name in args.scenes.split(","):
        rf = Rayfarm(scene_name, SIZES[scene_name], args.depth, args.workers)
        mask = emitter_mask(rf)
        ref_mean, ref_var = rayfarm_reference(rf, args.ref_spp, Path(args.refs))
        ladder = []
        for spp in args.ladder:
            film, _ = render_film(rf, spp, seed=11)
            ladder.append((spp, rmse(film.mean(), ref_mean, ref_var, mask)))
            print(f"{scene_name} raw {spp} spp: RMSE {ladder[-1][1]:.5f}", flush=True)
        lines += [f"## {scene_name}, {rf.width}x{rf.height}", "",
                  "| spp | raw RMSE | denoised RMSE | ratio | denoise s | equal-RMSE spp | saved "
                  "| display RMSE raw | display RMSE denoised |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for spp in args.spp:
            film, _ = render_film(rf, spp, seed=1)
            raw = rmse(film.mean(), ref_mean, ref_var, mask)
            t0 = time.perf_counter()
            clean = denoise_film(film)
            seconds = time.perf_counter() - t0
            den = rmse(clean.astype(np.float64), ref_mean, ref_var, mask)
            equal = equal_rmse_spp(ladder, den)
            lines.append(f"| {spp} | {raw:.5f} | {den:.5f} | {raw / den:.2f}x | {seconds:.2f} | "
                         + (f"{equal:.0f} | {equal / spp:.1f}x |" if equal else
                            f"> {args.ladder[-1]} | > {args.ladder[-1] / spp:.0f}x |")
                         + f" {display_rmse(film.mean(), ref_mean, mask):.5f} | "
                           f"{display_rmse(clean.astype(np.float64), ref_mean, mask):.5f} |")
            print(lines[-1], flush=True)
            if args.images:
                from PIL import Image

                out = Path(args.images)
                out.mkdir(parents=True, exist_ok=True)
                both = np.concatenate([tonemap_srgb8(film.mean()), tonemap_srgb8(clean)], axis=1)
                Image.fromarray(both).save(out / f"{scene_name}-{spp}spp-raw-vs-denoised.png")
        lines.append("")
    lines.append(READING)
    if args.out:
        Path(args.out).write_text("\n".join(lines))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
