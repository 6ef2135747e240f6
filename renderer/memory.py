"""What a job holds in memory, from the film's layout: the one formula that
admission (service.admission) checks against a role's limits.

    mem = job_memory(RenderSpec(method="bdpt", width=2048, height=2048, tile_size=64))
    mem.unit                  # bytes a render process holds for the job's largest unit
    mem.service(processes=8, waiting=128)  # bytes the service holds for the job at once
    mem.total(processes=8, waiting=128)    # and a unit in each of 8 render processes

A pure function of the request (spec, progressive, target, denoise): no
scene, no plan built. Each term is a layer of renderer/film.py's contract
times the pixels it spans, so a figure can be checked against the code
(tests/test_renderer_memory.py holds it above what tracemalloc measures).

A unit's film (what a render process returns, what the service stores):
- camera sums over the unit's region: sum, sum_sq (RGB) and weight, float64
  (56 bytes a pixel); the AOVs where the method has them (56 more); the
  jackknife sums of radiosity (J x 3 float64: 192 more);
- a splat batch over the *whole frame* for light tracing, BDPT (every tile
  unit!) and MLT's chains: splat and splat_sq, float64 (48 bytes a frame
  pixel), whatever the tile size;
- artefacts: SPPM's per-pixel state rides on every gather tile (176 bytes a
  pixel); photon records (40 bytes each) on photon units; MLT's bootstrap.

A render process's peak for a unit (beyond its own baseline, the interpreter,
Numba and the scene, about 220 MB, which no job changes): the film and the
method's scratch while it renders (the rasterizer's buffers, the splat
array's square, SPPM's visible points and state, each row's scratch), then
the film with its bytes (`to_bytes`, one copy), then the bytes with the
pipe's pickled message (pickle's buffer grows by half past the bytes: 2.5 x
the film in all traced, a little more resident; 2.75 counted); plus the
unit's inputs (photon maps, the previous round's state), decoded and as
bytes; plus `UNIT_BASE` for what every unit allocates whatever its size
(the sampler's memo, the camera: 2 to 12 MB measured; not a radiosity
solve's arrays, which are the scene's, not the frame's).

The service, for one job (see service.results, service.previews,
service.targets), the larger of:
- while units land: the running preview frame (float32, every layer of
  the film: 28 bytes a pixel and up), a progressive tile job's pass frame
  (float64 camera sums: 56), a preview write's channels and PNG, the films
  of the units finished and not yet collected (as bytes; the landed film
  the service reads is a view of them), as many as the executor keeps in
  flight (up to 16 a render process for short units: 64 light-tracing
  batches of 1024^2 pixels held 0.75 GB), and the pipe's message of each
  film a render process is handing over;
- the merge (renderer.stream): the float32 channels (28 or 56 bytes a
  pixel), the preview and noise PNGs' pixels (6), the error statistic's two
  float64 a pixel and its percentile's copy (25), PIL's copy while a PNG
  is encoded (4), the denoiser's inputs and output with `denoise` (72), and
  one band's sums and temporaries.

Measured against these figures: docs/hardening.md (bench/memory.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from . import images
from .images import AOV_CHANNELS
from .registry import METHODS
from .spec import RenderSpec

__all__ = ["JobMemory", "job_memory", "scene_memory", "UNIT_BASE", "SCENE_TRIANGLE"]

F64, F32 = 8, 4
CAMERA = 7 * F64  # sum, sum_sq (RGB) and weight
AOV = AOV_CHANNELS * F64
SPLAT = 6 * F64  # splat and splat_sq (RGB), per pixel of the frame
PHOTON_STATE = (1 + 1 + 3 + 3 + 3 + 3 + 1 + AOV_CHANNELS) * F64  # N, r2, tau, ld, s1, s2, M, aov
PHOTON_VISIBLE = (1 + 4 * 3 + 3 + 3 + 1) * F64 + 4  # a gather's visible points and sums
PHOTON_TEMPS = 24 * F64  # a gather's estimate films and the arithmetic making them
PHOTON_RECORD = 3 * 3 * F32 + 4  # position, direction, power (float32), hit count (int32)
PHOTON_GATHERED = 3 * 3 * F64 + 4 + 9 * F64  # a gathered photon as float64, and its grid cell
RASTER_SCRATCH = 4 * F64 + (6 + AOV_CHANNELS) * F64  # sample x/y, z, ids; a block's sums
ROW_SCRATCH = 32 << 10  # a unit's row: the path tracer's packet lanes and ring (29 KB), a BVH stack
SERIALIZED = 2.75  # a film's peak while it becomes bytes and a pipe message (module doc)
UNIT_BASE = 16 << 20  # what every unit allocates whatever its size (module doc)
ERROR = 2 * F64 + F64 + 1  # the statistic's level and error; the counted copy and mask
IMAGES = 2 * 3  # the preview's and the noise map's 8-bit RGB
PNG_ENCODE = 4  # PIL's RGBX copy of an image it encodes
DENOISE = 3 * F32 * 6  # colour, albedo, normal, output, its channels, OIDN's own
BAND = 1024  # a band's float64 sums, read rows and temporaries, per band pixel, at most
# A render process building a scene, per triangle: the decoded asset, world
# positions, the kernel arrays (210 bytes kept) and the BVH build's
# temporaries; 640 measured at 180k triangles (tracemalloc's peak of build_scene).
SCENE_TRIANGLE = 640


@dataclass(frozen=True)
class JobMemory:
    """Bytes a job holds (module doc). `unit_film`: the largest unit's film;
    `unit`: a render process's peak for it; `frames`: the service's frames
    of the job in flight; `merge`: the service's peak while it merges.
    `unit_frame`: the part of `unit` that a smaller tile does not shrink
    (whole-frame splats, photon maps), which admission names the frame for.
    `stored`: the bytes of all its unit films in the store, where they stay
    until the job is deleted (a comparison's passes and a partial result read
    them): a disk figure, not a memory one."""

    unit_film: int
    unit: int
    unit_frame: int
    frames: int
    merge: int
    stored: int = 0
    scene: int = 0  # the built scene in each render process (`scene_memory`)

    def service(self, processes: int, waiting: int | None = None) -> int:
        """The service's peak for the job with `processes` render processes
        handing films over and `waiting` finished units' films not yet
        collected (default: one a process)."""
        waiting = processes if waiting is None else waiting
        return max(self.frames + (waiting + processes) * self.unit_film, self.merge)

    def total(self, processes: int, waiting: int | None = None) -> int:
        """The service's peak plus a unit and the scene in each of `processes`
        render processes."""
        return self.service(processes, waiting) + processes * (self.unit + self.scene)


def _photon_records(spec: RenderSpec) -> int:
    """Records a photon leaves, as the photon pass sizes its arrays at first:
    one per bounce after the first hit, up to 4 (cornell-box measures about one)."""
    return max(1, min(spec.depth - 1, 4))


def scene_memory(doc: dict, asset_bytes: dict[str, int] | None = None) -> int:
    """Bytes a render process holds for a resolved scene beyond its baseline,
    from the document alone (no asset decoded): its triangles (`triangles`
    of a mesh shape) times SCENE_TRIANGLE, plus the bytes of the texture
    assets it names where `asset_bytes` (digest -> size) knows them. A
    document reduced to its camera may give `triangles` at the top level."""
    from .scene import triangle_count

    if "shapes" in doc:
        triangles = triangle_count(doc)
    else:
        triangles = int(doc.get("triangles", 0))
    textures = 0
    for tex in (doc.get("textures") or {}).values():
        if isinstance(tex, dict) and asset_bytes and tex.get("image") in asset_bytes:
            textures += asset_bytes[tex["image"]]
    return triangles * SCENE_TRIANGLE + textures


def job_memory(spec: RenderSpec, *, progressive: bool = False, target: bool = False,
               denoise: bool = False, scene: int = 0) -> JobMemory:
    """The bytes a job of `spec` holds (module doc). `target`: a noise-target
    job (tiles x canonical-block passes up to spec.spp, its max_spp);
    `scene`: what each render process holds for the scene (`scene_memory`)."""
    from .plan import largest_unit

    method = METHODS[spec.method]
    options = method.check_options(spec.options)
    pixels = spec.width * spec.height
    aov = bool(method.aovs)
    tile_px = min(spec.tile_size, spec.width) * min(spec.tile_size, spec.height)
    camera = CAMERA + (AOV if aov else 0)
    jackknife = 0
    if method.family == "radiosity":
        from .radiosity_solve import JACKKNIFE

        jackknife = JACKKNIFE * 3 * F64
        camera += jackknife
    splat = method.family in ("splat", "chains")
    # the largest unit: (region pixels, film bytes, scratch while it renders,
    # inputs, and the part of them a smaller tile would not shrink)
    region, frame_film, scratch, inputs, frame_part = 0, 0, 0, 0, 0
    rows = min(spec.tile_size, spec.height)  # the tallest unit's rows
    if method.family in ("tile", "radiosity"):
        region, rows = largest_unit(spec, progressive or target, small_passes=target)
        if method.name == "raster":
            scratch = region * RASTER_SCRATCH
    elif method.name == "bdpt":
        region = tile_px  # tiles x small passes: no grouping
        frame_film = pixels * SPLAT
        scratch = pixels * SPLAT // 2  # the square of the splats, before it is scaled
    elif method.name in ("light", "mlt"):
        frame_film = pixels * SPLAT
        scratch = pixels * SPLAT // 2
        if method.name == "mlt":  # the bootstrap unit's path weights and their resampling
            from .integrators.mlt import bootstrap_per_depth

            inputs = bootstrap_per_depth(spec, options) * (spec.depth + 1) * 5 * F64
    elif method.family == "photons":
        from .integrators.photon import (PHOTONMAP, _iterations_per_unit, _typed,
                                         photons_per_iteration)

        typed = _typed(options)
        photons = photons_per_iteration(spec, typed) * _photon_records(spec)
        region = tile_px
        if typed["mode"] == PHOTONMAP:  # every gather tile reads the whole map
            inputs = photons * (2 * PHOTON_RECORD + PHOTON_GATHERED)
        else:  # a round's photon units, the tile's previous state, one iteration gathered
            rounds = min(_iterations_per_unit(spec, typed), spec.spp)
            inputs = (2 * rounds * photons * PHOTON_RECORD + photons * PHOTON_GATHERED
                      + 2 * region * PHOTON_STATE)
            camera += PHOTON_STATE  # the state rides on the gather film
            scratch = region * (PHOTON_VISIBLE + PHOTON_STATE + CAMERA + AOV + PHOTON_TEMPS)
        frame_part = inputs
    unit_film = region * camera + frame_film
    stored = _stored(spec, progressive, target, method, options, camera, frame_film)
    if region:
        scratch += rows * ROW_SCRATCH
    unit = (UNIT_BASE + inputs
            + math.ceil(max(unit_film + scratch, SERIALIZED * unit_film)))
    frame_part += math.ceil(SERIALIZED * frame_film)

    channels = 7 + (AOV_CHANNELS if aov else 0)
    preview = F32 * (7 + (AOV_CHANNELS if aov else 0) + (6 if splat else 0)
                     + jackknife // F64)
    pass_frame = CAMERA if (progressive or target) and method.plan is _tile_plan() else 0
    band = images.BAND_PIXELS * BAND
    frames = pixels * (preview + pass_frame + F32 * channels + 3 + PNG_ENCODE) + band
    merge = (pixels * (F32 * channels + IMAGES + ERROR + PNG_ENCODE + (DENOISE if denoise else 0))
             + band)
    return JobMemory(unit_film=unit_film, unit=unit, unit_frame=UNIT_BASE + frame_part,
                     frames=frames, merge=merge, stored=stored, scene=scene)


def _stored(spec: RenderSpec, progressive: bool, target: bool, method, options: dict,
            camera: int, frame_film: int) -> int:
    """`JobMemory.stored`: every pass of a tile plan covers the frame once
    (camera sums of each pixel per pass); a splat method's units each carry a
    whole-frame splat film (BDPT: every tile of every pass); a photon job
    stores each iteration's photons and each gather round's frame of state."""
    from .plan import sample_passes, tile_pixels
    from .plan_size import plan_size

    pixels = spec.width * spec.height
    tiles = -(-spec.width // spec.tile_size) * -(-spec.height // spec.tile_size)
    if method.family in ("tile", "radiosity"):
        passes = len(sample_passes(spec.spp, progressive or target,
                                   0 if target else tile_pixels(spec)))
        return passes * pixels * camera
    if method.family == "photons":
        from .integrators.photon import (PHOTONMAP, _iterations_per_unit, _typed,
                                         photons_per_iteration)

        typed = _typed(options)
        records = photons_per_iteration(spec, typed) * _photon_records(spec) * PHOTON_RECORD
        if typed["mode"] == PHOTONMAP:
            return records + pixels * camera
        rounds = -(-spec.spp // _iterations_per_unit(spec, typed))
        return spec.spp * records + rounds * pixels * camera
    units = plan_size(spec, progressive)
    if method.name == "bdpt":  # tiles x passes, each with the frame's splats
        return (units // tiles) * pixels * camera + units * frame_film
    return units * frame_film  # light tracing, MLT: a few dozen whole-frame batches


def _tile_plan():
    from .integrators.tile import tile_plan

    return tile_plan
