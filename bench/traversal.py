"""Rays per second per core of the BVH alone, on path-tracing rays.

    python bench/traversal.py                     # cornell-box, veach-mis, cornell-mesh

The rays are the ones a path tracer traces: camera rays through every pixel,
then from each camera hit a cosine-distributed bounce ray (closest hit) and a
shadow ray to a point on the first light (any hit). They are made once,
then traced --repeat times on one thread; the figure is the median. The
same rays for every build, so a change to the BVH's layout or traversal is
measured on exactly the same work (bench/throughput.py measures whole
renders: shading, sampling and all).

Each kind of ray is traced twice: one ray at a time
(`geometry.intersect_arrays`, what every method but the path tracer uses)
and in packets of PACKET consecutive rays (`packet.packet_intersect`, the
path tracer's traversal; consecutive camera rays are neighbouring pixels,
consecutive bounce and shadow rays start from neighbouring pixels' hits).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from renderer.kernels.camera import camera_ray
from renderer.kernels.geometry import (
    STACK_SIZE,
    intersect_arrays,
    offset_origin,
    surface_at_arrays,
)
from renderer.kernels.lights import sample_light
from renderer.kernels.packet import PACKET, packet_intersect
from renderer.kernels.sampling import cosine_hemisphere, to_world


@njit(cache=False)
def _make_rays(sc, cam, width, height, seed):
    np.random.seed(seed)
    n = width * height
    cam_rays = np.zeros((n, 6))
    bounce = np.zeros((n, 6))
    shadow = np.zeros((n, 7))
    n_b = 0
    stack = np.zeros(STACK_SIZE, np.int64)
    for y in range(height):
        for x in range(width):
            dx, dy, dz = camera_ray(cam, width, height, x + np.random.random(), y + np.random.random())
            i = y * width + x
            cam_rays[i] = (cam[0], cam[1], cam[2], dx, dy, dz)
            t, prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect,
                                       sc.sph, stack, cam[0], cam[1], cam[2], dx, dy, dz,
                                       np.inf, False)
            if prim < 0:
                continue
            hx, hy, hz = cam[0] + t * dx, cam[1] + t * dy, cam[2] + t * dz
            nx, ny, nz, _, _ = surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light, sc.sph,
                                                 sc.sph_flip, sc.sph_mat, sc.sph_light, prim,
                                                 hx, hy, hz)
            if nx * dx + ny * dy + nz * dz > 0.0:
                nx, ny, nz = -nx, -ny, -nz
            lx, ly, lz = cosine_hemisphere(np.random.random(), np.random.random())
            wx, wy, wz = to_world(lx, ly, lz, nx, ny, nz)
            ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
            # a shadow ray towards a point on a light, as next event estimation picks it
            lx, ly, lz, dist, pdf, _, _, _, _ = sample_light(sc, ox, oy, oz, np.random.random(),
                                                            np.random.random())
            if pdf <= 0.0:
                continue
            bounce[n_b] = (ox, oy, oz, wx, wy, wz)
            shadow[n_b] = (ox, oy, oz, lx, ly, lz, dist * (1.0 - 1e-9))
            n_b += 1
    return cam_rays, bounce[:n_b].copy(), shadow[:n_b].copy()


@njit(cache=False)
def _trace(sc, rays, any_hit, out):
    stack = np.zeros(STACK_SIZE, np.int64)
    hits = 0
    for i in range(rays.shape[0]):
        tmax = rays[i, 6] if rays.shape[1] > 6 else np.inf
        _, prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                                   stack, rays[i, 0], rays[i, 1], rays[i, 2], rays[i, 3],
                                   rays[i, 4], rays[i, 5], tmax, any_hit)
        out[i] = prim
        hits += prim >= 0
    return hits


@njit(cache=False, error_model="numpy")
def _trace_packets(sc, rays, any_hit, out):
    """`_trace` in packets of PACKET consecutive rays (the last one padded
    with idle lanes)."""
    stack = np.zeros(STACK_SIZE, np.int64)
    lanes = np.zeros((10, PACKET))
    prim = np.zeros(PACKET, np.int64)
    act = np.zeros(PACKET, np.int64)
    hits = 0
    for base in range(0, rays.shape[0], PACKET):
        m = min(PACKET, rays.shape[0] - base)
        for r in range(PACKET):
            i = base + min(r, m - 1)
            for c in range(6):
                lanes[c, r] = rays[i, c]
            lanes[9, r] = rays[i, 6] if rays.shape[1] > 6 else np.inf
            act[r] = 1 if r < m else 0
        packet_intersect(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph, stack,
                         lanes[0], lanes[1], lanes[2], lanes[3], lanes[4], lanes[5], lanes[6],
                         lanes[7], lanes[8], lanes[9], prim, act, any_hit)
        for r in range(m):
            out[base + r] = prim[r]
            hits += prim[r] >= 0
    return hits


HEAVY = "cornell-mesh"
SIZES = {"cornell-box": (256, 256), "veach-mis": (256, 144), HEAVY: (256, 256)}


def load(name: str):
    from renderer import load_scene
    if name == HEAVY:
        import heavy_mesh
        return load_scene(heavy_mesh.scene_doc())
    return load_scene(name)


def measure(name: str, size: tuple[int, int], repeat: int) -> dict:
    from renderer.scene import camera_array

    t0 = time.perf_counter()
    scene = load(name)
    build = time.perf_counter() - t0
    sc = scene.arrays
    cam = camera_array(scene.camera, *size)
    cam_rays, bounce, shadow = _make_rays(sc, cam, size[0], size[1], 7)
    out = {"scene": name, "triangles": int(sc.tri_isect.shape[0]),
           "nodes": int(sc.bvh_nodes.shape[0]), "build_s": build}
    for label, rays, any_hit in (("camera", cam_rays, False), ("bounce", bounce, False),
                                 ("shadow", shadow, True)):
        for suffix, trace in (("", _trace), ("_packets", _trace_packets)):
            prims = np.zeros(len(rays), np.int64)
            trace(sc, rays[:PACKET], any_hit, prims)
            times = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                hits = trace(sc, rays, any_hit, prims)
                times.append(time.perf_counter() - t0)
            out[label + suffix] = (len(rays) / float(np.median(times)), hits / len(rays))
    return out


def table(sizes: dict, repeat: int):
    """The Markdown table, a line at a time (the rows as they are measured)."""
    yield ("| scene | triangles | wide BVH nodes | scene build s | camera rays/s | bounce rays/s "
           f"| shadow rays/s | camera, bounce, shadow rays/s in packets of {PACKET} |")
    yield "|---|---|---|---|---|---|---|---|"
    for name, size in sizes.items():
        r = measure(name, size, repeat)
        yield (f"| {name} | {r['triangles']} | {r['nodes']} | {r['build_s']:.2f} | "
               + " | ".join(f"{r[k][0] / 1e6:.2f} M ({100 * r[k][1]:.0f} % hit)"
                            for k in ("camera", "bounce", "shadow")) + " | "
               + " / ".join(f"{r[k + '_packets'][0] / 1e6:.2f} M"
                            for k in ("camera", "bounce", "shadow")) + " |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SIZES))
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    for line in table({name: SIZES[name] for name in args.scenes.split(",")}, args.repeat):
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
