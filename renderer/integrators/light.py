"""`light`: light tracing (forward path tracing), pbrt-v3's BDPT with t = 1 only.

    film = render_serial(load_scene("cornell-box"), RenderSpec(method="light", spp=16))

Each light path starts on a light (`sample_emission`: area lights from a
point and a cosine direction, point lights in a uniform direction) and
scatters through the scene with the adjoint BSDFs (importance transport: no
1/eta^2 on refraction). Every vertex, the light point itself included,
connects to the camera (the pinhole, or a point drawn on the thin lens) with
a shadow ray and splats (with the camera's filter: kernels/camera.py)
beta f |cos| We cos_cam / dist^2 onto the full frame (kernels/camera.py:
We is per pixel, so splats estimate the pixel's mean radiance, as a camera
sample of `path-mis` does). A path of depth d has at most d + 1 segments from
the light to the camera: the light subpath has at most depth + 1 vertices.

What light tracing cannot render: point lights seen directly (they have no
area; `path-mis` does not see them either) and anything the camera sees
through a mirror or glass (a specular vertex cannot connect to the pinhole):
such paths are missing, as in every pure light tracer.

Plan: N = width x height x spp light paths, cut into K equal ranges of path
indices (`light_batches`: K = 8 to 64 as N allows), each a unit whose film is
one splat batch over the full frame (`PartialFilm.splat_batch(splat, n)`).
The frame estimate divides the summed splats by the job's N (the merge does,
film.py) and the variance of a pixel comes from the K batches. Path p draws
its numbers from `stream_key(seed, STREAM_LIGHT_PATHS, p)`, dimension j of
the stream at u[light0(depth) + j] (the layout of the light subpath in
renderer/kernels/subpaths.py).
"""

from __future__ import annotations

import numpy as np

from ..film import PartialFilm
from ..kernels import kernel
from ..kernels.camera import CAM_LENS, splat_add
from ..kernels.geometry import STACK_SIZE
from ..kernels.rng import STREAM_LIGHT_PATHS, stream_key, uniform
from ..kernels.sampling import BALANCE
from ..kernels.subpaths import (
    NV,
    T_CAMERA,
    V_LIGHT,
    V_MAT,
    V_TYPE,
    conn0,
    connect,
    dims,
    light0,
    light_subpath,
    workspace,
)
from ..plan import Unit
from ..registry import Method
from ..scene import camera_array

MIN_BATCHES, MAX_BATCHES = 8, 64
PATHS_PER_BATCH = 4096  # below 8 x this many paths, batches shrink instead of dropping below 8


def light_batches(n_paths: int) -> int:
    """How many units (splat batches) a job of n_paths light paths gets."""
    return max(1, min(n_paths, max(MIN_BATCHES, min(MAX_BATCHES, n_paths // PATHS_PER_BATCH))))


def plan_light(spec, progressive: bool = False, options: dict | None = None) -> list[Unit]:
    """K units of consecutive light-path indices, each splatting the full frame.
    (One pass: progressive jobs get the same plan.)"""
    n = spec.width * spec.height * spec.spp
    k = light_batches(n)
    return [Unit(i, 0, 0, spec.width, spec.height, n * i // k, n * (i + 1) // k, 0, 0, "splat")
            for i in range(k)]


@kernel
def _trace_light_paths(sc, cam, width, height, seed, depth, p0, p1, splat, u, V, stack):
    """Light paths p0 .. p1 - 1 splatted into `splat` (H, W, 3); returns rays."""
    lrow = depth + 2
    srow = 2 * (depth + 2)
    l0 = light0(depth)
    c0 = conn0(depth)
    for c in range(NV):
        V[0, c] = 0.0
    V[0, 0], V[0, 1], V[0, 2] = cam[0], cam[1], cam[2]
    V[0, V_TYPE] = T_CAMERA
    V[0, V_MAT] = -1.0
    V[0, V_LIGHT] = -1.0
    rays = 0
    for p in range(p0, p1):
        key = stream_key(seed, STREAM_LIGHT_PATHS, p)
        for d in range(l0, c0):
            u[d] = uniform(key, d - l0)
        nl, nr = light_subpath(sc, stack, V, lrow, depth + 1, u, l0)
        rays += nr
        for s in range(1, nl + 1):
            if cam[CAM_LENS] > 0.0:  # the lens point of this connection: u[1], u[2]
                u[1] = uniform(key, c0 - l0 + 2 * s)
                u[2] = uniform(key, c0 - l0 + 2 * s + 1)
            r, g, b, fx, fy, nr = connect(sc, cam, width, height, stack, V, lrow, srow, s, 1, u,
                                          0, BALANCE, False)
            rays += nr
            if r != 0.0 or g != 0.0 or b != 0.0:
                splat_add(splat, cam, fx, fy, r, g, b)
    return rays


def render_light(scene, spec, unit, inputs=None, options=None) -> PartialFilm:
    """One unit of `light`: light paths [sample_start, sample_end) as a splat batch."""
    splat = np.zeros((spec.height, spec.width, 3))
    cam = camera_array(scene.camera, spec.width, spec.height)
    u = np.zeros(dims(spec.depth))
    V = workspace(spec.depth)
    stack = np.empty(STACK_SIZE, np.int64)
    rays = _trace_light_paths(scene.arrays, cam, spec.width, spec.height, spec.seed, spec.depth,
                              unit.sample_start, unit.sample_end, splat, u, V, stack)
    n = unit.sample_end - unit.sample_start
    film = PartialFilm.splat_batch(splat, n)
    film.stats.update(samples=n, rays=int(rays))
    return film


METHODS = (Method(
    name="light",
    aov_note="its image is splatted from light paths: no camera sample of "
             "a pixel has a first hit to take albedo, normal or depth from",
    description="Light tracing: paths start on lights and every vertex connects to the "
                "camera (pinhole or thin lens), splatting anywhere on the image.",
    run=render_light,
    family="splat",
    plan=plan_light,
    phases=("splat",),
),)
