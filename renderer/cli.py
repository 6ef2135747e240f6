"""`rayfarm render` / `python -m renderer`: render a scene locally.

    rayfarm render cornell-box --method path --spp 64 --depth 7 --tile-size 32 \\
        --seed 1 --out cornell.exr

The job goes through the same plan -> units -> merge path as on the farm,
on a local process pool (one process per core), and writes the EXR and a
tonemapped PNG preview next to it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .errors import RenderError, SceneError
from .importers import import_scene
from .registry import METHODS, SAMPLERS
from .scene_format import builtin_scene_names, resolve_document
from .spec import RenderSpec, default_depth

IMPORTED_SUFFIXES = (".xml", ".gltf", ".glb")  # scene files an importer turns into documents

__all__ = ["main", "build_parser"]


def build_parser(prog: str = "rayfarm render") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Render a scene locally through the "
                                "farm's plan -> units -> merge path.")
    p.add_argument("scene", help=f"built-in scene ({', '.join(builtin_scene_names())}) "
                                 "or a path to a scene file (.json, Mitsuba .xml, .gltf, .glb)")
    p.add_argument("--method", default="path", choices=sorted(METHODS))
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a method option, e.g. --option heuristic=balance (repeatable)")
    p.add_argument("--sampler", default=RenderSpec().sampler, choices=sorted(SAMPLERS))
    p.add_argument("--spp", type=int, default=16, help="samples per pixel")
    p.add_argument("--depth", type=int, default=None,
                   help="surface bounces: 0 = emitters only, 1 = direct light (default: the "
                        "scene's, from an imported file's integrator block, else 5)")
    p.add_argument("--tile-size", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, help="override the scene camera's width")
    p.add_argument("--height", type=int, help="override the scene camera's height")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--out", default="render.exr", help="output EXR path (PNG preview beside it)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--target", type=float, metavar="REL_ERROR",
                   help="render to a noise target instead of a fixed spp: add sample passes, "
                        "tile by tile, until the 95th percentile of the pixels' relative "
                        "standard error is at most REL_ERROR (e.g. 0.05); --spp is then the "
                        "most samples per pixel (renderer/target.py)")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="with --target: stop adding passes after this long")
    p.add_argument("--denoise", action="store_true",
                   help="also write denoised.R/G/B (Open Image Denoise over the whole frame, "
                        "with the albedo and normal AOVs) and <out>.denoised.png")
    return p


def _typed_options(method: str, options: dict[str, str]) -> dict:
    """`--option` values typed by the method's option table (int, float);
    unknown methods and options stay strings, for validate() to name."""
    from .errors import SpecError
    from .registry import METHODS

    if method not in METHODS:
        return options
    types = {o.name: o.type for o in METHODS[method].options}
    out = {}
    for key, value in options.items():
        kind = types.get(key, str)
        try:
            out[key] = kind(value) if kind in (int, float) else value
        except ValueError:
            raise SpecError(f"options.{key}", f"expects {kind.__name__}, got {value!r}") from None
    return out


def load_scene(scene: str) -> dict:
    """The resolved document of a built-in scene or a scene file; an
    imported file's (Mitsuba XML, glTF) report is printed to stderr."""
    path = Path(scene)
    if path.suffix.lower() not in IMPORTED_SUFFIXES:
        return resolve_document(scene)
    if not path.is_file():
        raise SceneError(f"no such scene file: {scene}")
    imported = import_scene(path)
    for entry in imported.report:
        print(f"import: {entry}", file=sys.stderr)
    return resolve_document(imported.doc, base_dir=path.parent, assets=imported.assets)


def main(argv: list[str] | None = None, prog: str = "rayfarm render") -> int:
    args = build_parser(prog).parse_args(argv)
    from .local import render
    from .metadata import exr_metadata
    from .registry import METHODS
    from .runtime import scene_text

    options = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep:
            print(f"error: --option expects KEY=VALUE, got {item!r}", file=sys.stderr)
            return 2
        options[key] = value
    try:
        options = _typed_options(args.method, options)
        doc = load_scene(args.scene)
        cam = doc["camera"]
        depth = args.depth if args.depth is not None else default_depth(doc)
        spec = RenderSpec(method=args.method, spp=args.spp, depth=depth,
                          width=args.width or cam["width"], height=args.height or cam["height"],
                          tile_size=args.tile_size, seed=args.seed, sampler=args.sampler,
                          options=options).validate(scene=doc)
    except RenderError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.suffix.lower() != ".exr":
        print("error: --out must name an .exr file", file=sys.stderr)
        return 2
    out.parent.mkdir(parents=True, exist_ok=True)

    from tqdm import tqdm

    t0 = time.perf_counter()
    target = None
    if args.target is not None:
        from .target import Target, render_to_target

        try:
            target = Target(args.target, spec.spp, args.max_seconds).validate()
            film, report = render_to_target(
                doc, spec, target, workers=args.workers,
                progress=None if args.quiet else lambda p, e: print(
                    f"pass {p}: error {100 * e:.2f} % (target {100 * target.rel_error:.2f} %)",
                    file=sys.stderr))
        except RenderError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(f"target: {report.stopped} after {report.passes} passes; {report.units_run} "
              f"units run, {report.units_skipped} skipped; spp per pixel "
              f"{int(film.weight.min())}..{int(film.weight.max())}")
    else:
        units = METHODS[spec.method].make_plan(spec, False)
        bar = tqdm(total=len(units), unit="unit", disable=args.quiet,
                   desc=f"{args.scene} {spec.method}")
        film = render(doc, spec, workers=args.workers, progress=lambda unit, part: bar.update(1))
        bar.close()
    seconds = time.perf_counter() - t0
    clean = None
    if args.denoise:
        from .denoise import denoise_film

        clean = denoise_film(film)
        film.write_png(out.with_suffix(".denoised.png"), clean)
    error = film.image_error()
    film.write_exr(out, exr_metadata(spec, film.stats, scene=doc.get("name") or str(args.scene),
                                     scene_hash=scene_text(doc)[0], rel_error=error,
                                     target=target, denoised=clean is not None),
                   denoised=clean)
    film.write_png(out.with_suffix(".png"))
    s = film.stats
    print(f"wrote {out} and {out.with_suffix('.png')}: {spec.width}x{spec.height}, {spec.spp} spp, "
          f"depth {spec.depth}, {seconds:.2f} s wall, {s['samples'] / seconds:,.0f} samples/s, "
          f"{s['rays'] / seconds:,.0f} rays/s, error {100 * error:.2f} % (95th percentile of "
          f"the pixels' relative standard error)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
