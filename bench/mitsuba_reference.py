"""Reference renders of `cornell-box` with Mitsuba 3, for checking our kernels.

Builds the Mitsuba scene from rayfarm's own scene document (so it is the very
scene our renderer sees: same matrices, materials, emitter, camera), checks it
against `mi.cornell_box()` and against the camera-ray table of
/work/shared/scenes/cornell-box.md, then renders it with the `path`
integrator at max_depth = depth + 1 (our depth convention), a box pixel
filter and the `independent` sampler. Each depth is rendered as `--seeds`
independent passes; the saved image is their mean and the standard error is
the standard deviation of the pass means over sqrt(passes).

    python bench/mitsuba_reference.py                      # depths 0, 1, 7
    python bench/mitsuba_reference.py --depth 7:8192 --seeds 32 --out /tmp/refs
    python bench/mitsuba_reference.py --xml ../shared/scenes/real/veach-bidir/scene.xml \
        --size 256x256 --spp 4096 --out /tmp/refs      # a user's Mitsuba file, as written

With --xml, Mitsuba renders the file itself, the way the shared scenes'
README prescribes: the `<mode>` element removed and the integrator replaced
by a plain `path` of the file's own max depth (Mitsuba 3 refuses those
files' integrator blocks), the film resized with --size. Writes
<out>/<folder>_<W>x<H>_spp<N>.npy, its _stderr.npy and an .exr of the mean.

Outputs (float32 .npy, shape (H, W, 3), row 0 at the top):
    <out>/cornell_d{d}_spp{N}.npy          mean radiance
    <out>/cornell_d{d}_spp{N}_stderr.npy   standard error of that mean
Russian roulette is off (rr_depth > max_depth): unbiased either way, but
without it the reference converges faster per sample.
Needs `pip install -e '.[mitsuba]'`; the LLVM variant needs libLLVM >= 19
(Debian: `apt-get install libllvm19`), otherwise `scalar_rgb` is used.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_OUT = "/work/shared-refs"
DEFAULT_DEPTHS = "0:1024,1:4096,7:8192"

# (film px, py) -> ray direction, from the table in shared/scenes/cornell-box.md
RAY_TABLE = [
    ((0.5, 0.5), (-0.3177954, 0.3177954, -0.8933153)),
    ((255.5, 0.5), (0.3177954, 0.3177954, -0.8933153)),
    ((128.0, 128.0), (0.0, 0.0, -1.0)),
    ((128.5, 128.5), (0.0013951, -0.0013951, -0.9999981)),
    ((0.5, 255.5), (-0.3177954, -0.3177954, -0.8933153)),
    ((30.5, 128.5), (-0.2625024, -0.0013462, -0.9649304)),
]


def choose_variant(preferred: str | None = None) -> str:
    """Set and return the Mitsuba variant: `llvm_ad_rgb` if it renders, else `scalar_rgb`."""
    import mitsuba as mi

    llvm = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
    if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(llvm):
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm  # older libLLVMs on the path crash Dr.Jit
    candidates = [preferred] if preferred else ["llvm_ad_rgb", "scalar_rgb"]
    for variant in candidates:
        if variant not in mi.variants():
            continue
        if variant.startswith("llvm") and not _renders_in_child(variant):
            # an LLVM too old for Dr.Jit aborts the process ("LLVM ERROR: Cannot
            # select: fminimum", libLLVM 14/15 with Dr.Jit 1.5): no exception to catch
            print(f"mitsuba variant {variant} unusable: its JIT aborted a test render "
                  "(libLLVM >= 19 needed)", file=sys.stderr)
            continue
        try:
            mi.set_variant(variant)
            mi.render(mi.load_dict(mi.cornell_box()), spp=1)  # a variant may load yet fail to JIT
            return variant
        except Exception as exc:  # noqa: BLE001 - report and fall back
            print(f"mitsuba variant {variant} unusable: {exc}", file=sys.stderr)
    raise RuntimeError(f"no usable Mitsuba variant among {candidates}")


def _renders_in_child(variant: str) -> bool:
    """Does `variant` render a tiny Cornell box in a child process?"""
    code = ("import mitsuba as mi; mi.set_variant(%r); "
            "mi.render(mi.load_dict(mi.cornell_box()), spp=1)" % variant)
    try:
        return subprocess.run([sys.executable, "-c", code], capture_output=True,
                              timeout=600).returncode == 0
    except subprocess.TimeoutExpired:
        return False


def mitsuba_scene_dict(doc: dict, depth: int, spp: int = 1, rr_depth: int | None = None) -> dict:
    """A Mitsuba scene dict for a resolved rayfarm scene document (rectangles,
    cubes, spheres; diffuse, glossy, mirror and glass materials; area
    emitters; a pinhole camera). `rr_depth` None keeps Mitsuba's default
    Russian roulette (from depth 5); the references here switch it off.

    `glossy` becomes `roughconductor` with its distribution, alpha = our
    roughness and no Fresnel (`material: none`, times the specular colour):
    rayfarm's glossy uses Schlick's Fresnel from that colour and Smith's
    height-correlated G2, Mitsuba a constant colour and the separable G1 G1,
    so glossy scenes are close, not equal (kernels/ggx.py)."""
    import mitsuba as mi

    cam = doc["camera"]
    T = mi.ScalarTransform4f
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": depth + 1,
                       **({} if rr_depth is None else {"rr_depth": rr_depth})},
        "sensor": {
            "type": "perspective",
            "fov": float(cam["fov"]),
            "fov_axis": cam.get("fov_axis", "smaller"),
            "near_clip": 0.001, "far_clip": 100.0,
            "to_world": T().look_at(origin=cam["origin"], target=cam["target"], up=cam["up"]),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {"type": "hdrfilm", "width": int(cam["width"]), "height": int(cam["height"]),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb",
                     "component_format": "float32"},
        },
    }
    for name, mat in doc["materials"].items():
        if mat["type"] == "diffuse":
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(mat["albedo"])}}
        elif mat["type"] == "glossy":
            bsdf = {"type": "roughconductor", "distribution": mat.get("distribution", "ggx"),
                    "material": "none",
                    "alpha": float(mat["roughness"]),
                    "specular_reflectance": {"type": "rgb", "value": list(mat["specular"])}}
        elif mat["type"] == "mirror":
            bsdf = {"type": "conductor", "material": "none",
                    "specular_reflectance": {"type": "rgb", "value": list(mat["tint"])}}
        elif mat["type"] == "dielectric":
            bsdf = {"type": "dielectric", "int_ior": float(mat["ior"]), "ext_ior": 1.0}
        else:
            raise ValueError(f"material {name}: type {mat['type']} is not translated")
        scene[f"mat-{name}"] = {**bsdf, "id": f"mat-{name}"}
    for shape in doc["shapes"]:
        if shape["type"] not in ("rectangle", "cube", "sphere"):
            raise ValueError(f"shape {shape['name']}: type {shape['type']} is not translated")
        if shape["type"] == "sphere":
            if np.any(np.array(shape["to_world"], dtype=float) != np.eye(4)):
                raise ValueError(f"shape {shape['name']}: a transformed sphere is not translated")
            entry = {"type": "sphere", "center": list(shape["center"]), "radius": float(shape["radius"]),
                     "bsdf": {"type": "ref", "id": f"mat-{shape['material']}"}}
        else:
            entry = {"type": shape["type"], "to_world": T(np.array(shape["to_world"], dtype=float)),
                     "bsdf": {"type": "ref", "id": f"mat-{shape['material']}"}}
        if shape.get("emitter"):
            entry["emitter"] = {"type": "area", "radiance": {
                "type": "rgb", "value": list(shape["emitter"]["radiance"])}}
        scene[shape["name"].replace(".", "_")] = entry  # "." delimits Mitsuba object paths
    if doc.get("emitters"):
        raise ValueError("standalone emitters are not translated")
    return scene


def check_scene(scene) -> float:
    """Compare camera rays with the table in cornell-box.md and shape bounds
    with `mi.cornell_box()`; print both and return the largest deviation."""
    import mitsuba as mi

    sensor = scene.sensors()[0]
    size = sensor.film().size()
    worst = 0.0
    print("camera rays (film px, py): mitsuba direction vs cornell-box.md")
    for (px, py), expected in RAY_TABLE:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(px / size[0], py / size[1]),
                                   mi.Point2f(0.5, 0.5))
        d = np.array(ray.d, dtype=float).reshape(-1)[:3]
        err = float(np.abs(d - np.array(expected)).max())
        worst = max(worst, err)
        print(f"  ({px:6.1f},{py:6.1f})  {np.round(d, 7)}  {expected}  |diff| {err:.1e}")
    builtin = mi.load_dict(mi.cornell_box())
    bounds = lambda s: sorted(  # noqa: E731
        tuple(np.round(np.concatenate([np.array(sh.bbox().min), np.array(sh.bbox().max)]).ravel(), 4))
        for sh in s.shapes())
    ours, theirs = bounds(scene), bounds(builtin)
    shape_err = max(float(np.abs(np.array(a) - np.array(b)).max()) for a, b in zip(ours, theirs))
    print(f"shape bounding boxes vs mi.cornell_box(): {len(ours)} vs {len(theirs)} shapes, "
          f"max |diff| {shape_err:.1e}")
    if len(ours) != len(theirs):
        shape_err = math.inf
    return max(worst, shape_err)


def render_passes(scene, spp: int, passes: int, seed0: int = 0):
    """Render `passes` independent passes of spp // passes samples each; return
    (mean image, standard error of the mean, seconds)."""
    import mitsuba as mi

    per_pass = spp // passes
    images = []
    t0 = time.perf_counter()
    for k in range(passes):
        img = mi.render(scene, spp=per_pass, seed=seed0 + k)
        images.append(np.array(img, dtype=np.float64)[..., :3])
    seconds = time.perf_counter() - t0
    stack = np.stack(images)
    mean = stack.mean(axis=0)
    stderr = stack.std(axis=0, ddof=1) / math.sqrt(passes) if passes > 1 else np.full_like(mean, np.nan)
    return mean.astype(np.float32), stderr.astype(np.float32), seconds


def xml_scene(path: Path, size: tuple[int, int] | None, max_depth: int | None = None):
    """Load a Mitsuba XML file as the README of the shared scenes prescribes:
    no `<mode>`, a plain `path` integrator of the file's max depth (after
    `<default>` substitution), the film resized to `size`. Returns
    (scene, max_depth)."""
    import xml.etree.ElementTree as ET  # our own reference tool, run on files we trust

    import mitsuba as mi

    root = ET.parse(path).getroot()
    defaults = {d.get("name"): d.get("value") for d in root.findall("default")}
    for mode in root.findall("mode"):
        root.remove(mode)
    depth = max_depth
    for integrator in root.findall("integrator"):
        for prop in integrator:
            if prop.get("name") in ("maxDepth", "max_depth") and depth is None:
                value = prop.get("value", "")
                depth = int(defaults.get(value[1:], value) if value.startswith("$") else value)
        root.remove(integrator)
    depth = -1 if depth is None else depth
    ET.SubElement(root, "integrator", type="path").append(
        ET.Element("integer", name="max_depth", value=str(depth)))
    # What Mitsuba 3 refuses in files written for 0.5/0.6, removed where that
    # changes nothing: veach-bidir's `<hide>` (a property switched off by its
    # tag) and a conductor's `extEta` of 1 (Mitsuba 3's conductors border vacuum)
    for parent in root.iter():
        if parent.tag == "bsdf" and parent.get("type") == "roughdiffuse":
            # Mitsuba 3 has no Oren-Nayar: the reference itself is then approximate
            print("mitsuba_reference: roughdiffuse rendered as Mitsuba 3's diffuse", file=sys.stderr)
            parent.set("type", "diffuse")
            for child in list(parent):
                if child.get("name") in ("alpha", "useFastApprox", "use_fast_approx"):
                    parent.remove(child)
        if parent.tag == "string" and parent.get("name") in ("filterType", "filter_type") \
                and parent.get("value") in ("trilinear", "ewa"):
            parent.set("value", "bilinear")  # Mitsuba 3 has no MIP maps
        for child in list(parent):
            if parent.tag == "emitter" and child.get("name") in ("sunRadiusScale",
                                                                 "sun_radius_scale"):
                print("mitsuba_reference: Mitsuba 3's sunsky has no sunRadiusScale: dropped",
                      file=sys.stderr)
                parent.remove(child)
            elif child.tag == "hide":
                parent.remove(child)
            elif (parent.tag == "bsdf" and "conductor" in parent.get("type", "")
                  and child.get("name") in ("extEta", "ext_eta")):
                if float(child.get("value")) != 1.0:
                    raise ValueError(f"a conductor's {child.get('name')} of {child.get('value')}: "
                                     "Mitsuba 3 has none")
                parent.remove(child)
    if int(root.get("version", "3").split(".")[0]) < 2:
        for emitter in root.iter("emitter"):
            if emitter.get("type") == "sunsky" and emitter.find("transform") is None:
                # 0.5/0.6's sky has its zenith on +y, Mitsuba 3's on its local +z (its
                # sun_direction stays in world space): without this the sun of
                # classroom is below the horizon and the render black
                print("mitsuba_reference: sunsky turned to Mitsuba 0.6's zenith +y",
                      file=sys.stderr)
                rotate = ET.Element("rotate", x="1", angle="-90")
                ET.SubElement(emitter, "transform", name="to_world").append(rotate)
    for film in root.iter("film"):
        # Mitsuba 3 has only `hdrfilm`: keep the size and the filter, drop the
        # LDR output settings (gamma, file format, banner) it would refuse
        film.set("type", "hdrfilm")
        for prop in list(film):
            name = prop.get("name")
            if prop.tag == "integer" and name in ("width", "height"):
                if size is not None:
                    prop.set("value", str(size[0] if name == "width" else size[1]))
            elif prop.tag != "rfilter":
                film.remove(prop)
    mi.file_resolver().prepend(str(path.parent.resolve()))
    return mi.load_string(ET.tostring(root, encoding="unicode")), depth


def xml_main(args) -> int:
    import mitsuba as mi

    variant = choose_variant(args.variant)
    path = Path(args.xml)
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    scene, depth = xml_scene(path, size)
    passes = max(1, min(args.seeds, args.spp))
    spp = args.spp - args.spp % passes
    mean, stderr, seconds = render_passes(scene, spp, passes)
    h, w = mean.shape[:2]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{path.parent.name}_{w}x{h}_spp{spp}"
    np.save(f"{stem}.npy", mean)
    np.save(f"{stem}_stderr.npy", stderr)
    mi.Bitmap(mean).write(f"{stem}.exr")
    print(f"mitsuba {mi.__version__} ({variant}): {path}, path max_depth {depth}, {w}x{h}, "
          f"{spp} spp in {passes} passes, {seconds:.1f} s; wrote {stem}.npy, _stderr.npy, .exr")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--depth", default=DEFAULT_DEPTHS,
                        help=f"comma list of depth:spp (default {DEFAULT_DEPTHS})")
    parser.add_argument("--seeds", type=int, default=16,
                        help="independent passes per depth, for the standard error (default 16)")
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"output directory (default {DEFAULT_OUT})")
    parser.add_argument("--variant", default=None, help="Mitsuba variant (default: llvm_ad_rgb, else scalar_rgb)")
    parser.add_argument("--scene", default="cornell-box")
    parser.add_argument("--xml", help="render this Mitsuba XML file instead (see above)")
    parser.add_argument("--size", help="with --xml: the film's WxH (default: the file's)")
    parser.add_argument("--spp", type=int, default=1024, help="with --xml: samples per pixel")
    args = parser.parse_args(argv)
    if args.xml:
        return xml_main(args)

    import mitsuba as mi

    from renderer import resolve_document

    variant = choose_variant(args.variant)
    print(f"mitsuba {mi.__version__}, variant {variant}")
    doc = resolve_document(args.scene)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    checked = False
    for item in args.depth.split(","):
        depth, spp = (int(v) for v in item.split(":"))
        passes = max(1, min(args.seeds, spp))
        spp -= spp % passes
        scene = mi.load_dict(mitsuba_scene_dict(doc, depth, rr_depth=depth + 2))
        if not checked:
            worst = check_scene(scene)
            if worst > 1e-5:
                print(f"scene check FAILED (max deviation {worst:.2e})", file=sys.stderr)
                return 1
            checked = True
        mean, stderr, seconds = render_passes(scene, spp, passes)
        stem = out / f"{args.scene.replace('-box', '')}_d{depth}_spp{spp}"
        np.save(f"{stem}.npy", mean)
        np.save(f"{stem}_stderr.npy", stderr)
        pixels = mean.shape[0] * mean.shape[1]
        ch = mean.reshape(-1, 3).mean(axis=0)
        ch_err = np.sqrt((stderr.reshape(-1, 3).astype(np.float64) ** 2).sum(axis=0)) / pixels
        print(f"depth {depth} (max_depth {depth + 1}), {spp} spp in {passes} passes, "
              f"{seconds:.1f} s, {pixels * spp / seconds / 1e6:.2f} M samples/s")
        print(f"  image mean R G B = {ch[0]:.6f} {ch[1]:.6f} {ch[2]:.6f}  "
              f"(+- {ch_err[0]:.1e} {ch_err[1]:.1e} {ch_err[2]:.1e})")
        print(f"  median per-pixel stderr / mean (G): "
              f"{float(np.median(stderr[..., 1] / np.maximum(mean[..., 1], 1e-12))):.4f}")
        print(f"  wrote {stem}.npy and {stem}_stderr.npy")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
