"""Opacity masks: a hit on a partly transparent surface is kept or passed
while the ray is traced, so every ray (camera, bounce, shadow, connection,
photon) meets the same cut-out surface.

    t, prim = trace(sc, stack, ox, oy, oz, dx, dy, dz, tmax)    # the closest kept hit
    hidden = blocked(sc, stack, ox, oy, oz, dx, dy, dz, tmax)   # a shadow ray

pbrt-v4's alpha test (GeometricPrimitive::Intersect): a hit on a surface of
opacity a is kept with probability a, decided by a hash of the ray (pbrt's
HashFloat(o, d)), so the decision is a pure function of the ray and a render
stays replayable and tiling-invariant; a == 1 is never tested and a == 0
always passed. A passed hit is no vertex of the path: the ray goes on from
just beyond it, the same line, so it costs no bounce and no random number.

The traversal kernels know nothing of it (geometry.intersect_arrays,
packet.packet_intersect). A hit they return is looked at only when its
material's flag `mat_masked` is set (`masked`); then `pass_masks` tests it
and, if it is passed, traces on from beyond it. Scenes without masks pay
the flag's load per hit (the path tracer's packets not even that: it asks
`has_masks` once per tile). Measured on cornell-box (path-mis 128 x 128 at
256 spp, one thread, ten interleaved pairs of processes on a loaded
2-core VM, 2026-12-08): +1.0 % CPU time (standard error 0.7 %), the same
film bytes; bdpt -0.6 %, photon +1.9 % (eight pairs each, within noise).

Each continuation is a ray of its own, hashed anew, so two masked surfaces
along one line are decided independently. (pbrt-v4 hashes the one ray its
traversal was given for every primitive along it: two stacked leaves of
opacity 1/2 let half of the rays through, not a quarter.) A shadow ray
that meets a masked surface first is traced again nearest hit first, since
an any-hit traversal cannot say what lies between its origin and its hit.

The opacity: the material's constant, or its texture's value at the hit's
uv (as Mitsuba 3's `eval_1`: the luminance of an RGB texture, the value of
a one-channel one); with a cutoff c > 0 (glTF's alphaMode MASK) it is 1
where that value is >= c and 0 elsewhere, a threshold, not a probability.
"""

import math

import numpy as np

from . import kernel, kernel_inline
from .geometry import intersect_arrays
from .rng import mix64
from .shading import hit_uv, tex_value

# the opacity's columns of mat_param (scene.py): the constant, the cutoff
MAT_OPACITY, MAT_CUTOFF = 2, 3
# a passed hit's continuation starts at eps / max(|cos|, MIN_COS) beyond it
# along the ray, eps being offset_origin's: eps from the surface, or less at
# grazing angles (where `pass_masks` also never tests a triangle twice)
MIN_COS = 1e-3
_SEED = np.uint64(0x5851F42D4C957F2D)
_STEP = np.uint64(0x9E3779B97F4A7C15)
_S11 = np.uint64(11)
_INV_2_53 = 1.0 / 9007199254740992.0
_TWO_53 = 9007199254740992.0


@kernel_inline
def _bits(x):
    """An integer that identifies the float x (its exact mantissa and exponent)."""
    m, e = math.frexp(x)
    return np.uint64(np.int64(m * _TWO_53)) ^ (np.uint64(e & 0xFFF) << np.uint64(53))


@kernel
def hash_ray(ox, oy, oz, dx, dy, dz):
    """A uniform float in [0, 1) that is a function of the ray's six floats."""
    h = mix64(_SEED ^ _bits(ox))
    h = mix64((h + _STEP) ^ _bits(oy))
    h = mix64((h + _STEP) ^ _bits(oz))
    h = mix64((h + _STEP) ^ _bits(dx))
    h = mix64((h + _STEP) ^ _bits(dy))
    h = mix64((h + _STEP) ^ _bits(dz))
    return float(h >> _S11) * _INV_2_53


@kernel_inline
def material_of(sc, prim):
    n_tri = sc.tri_mat.shape[0]
    return sc.tri_mat[prim] if prim < n_tri else sc.sph_mat[prim - n_tri]


@kernel_inline
def masked(sc, prim):
    """True if the material of primitive `prim` (>= 0) has an opacity mask."""
    return sc.mat_masked[material_of(sc, prim)] != 0


@kernel
def has_masks(mat_masked):
    for m in range(mat_masked.shape[0]):
        if mat_masked[m] != 0:
            return True
    return False


@kernel
def opacity(sc, prim, mat, hx, hy, hz):
    """The opacity of material `mat` at the point h of primitive `prim`."""
    a = sc.mat_param[mat, MAT_OPACITY]
    tex = sc.mat_tex[mat, 2]
    if tex >= 0:
        u, v = hit_uv(sc, prim, hx, hy, hz)
        a = tex_value(sc.tex_info, sc.tex_data, tex, u, v)
    cut = sc.mat_param[mat, MAT_CUTOFF]
    if cut > 0.0:
        a = 1.0 if a >= cut else 0.0
    return a


@kernel
def pass_masks(sc, stack, ox, oy, oz, dx, dy, dz, tmax, t, prim):
    """The closest hit the masks keep on the ray o + s d, s in (0, tmax),
    given the traversal's closest hit (t, prim): (t, prim), or (inf, -1)."""
    n_tri = sc.tri_mat.shape[0]
    base = 0.0  # where the present ray starts along the first one
    sx, sy, sz = ox, oy, oz
    passed = -1
    while prim >= 0:
        mat = material_of(sc, prim)
        if sc.mat_masked[mat] == 0:
            break
        s = base + t
        hx, hy, hz = ox + s * dx, oy + s * dy, oz + s * dz
        # a line meets a triangle once: the same one again is rounding, passed again
        if prim != passed or prim >= n_tri:
            a = opacity(sc, prim, mat, hx, hy, hz)
            if a >= 1.0 or (a > 0.0 and hash_ray(sx, sy, sz, dx, dy, dz) < a):
                break
        if prim < n_tri:
            nx, ny, nz = sc.tri_n[prim, 0], sc.tri_n[prim, 1], sc.tri_n[prim, 2]
        else:
            q = prim - n_tri
            nx, ny, nz = hx - sc.sph[q, 0], hy - sc.sph[q, 1], hz - sc.sph[q, 2]
            inv = 1.0 / sc.sph[q, 3]
            nx, ny, nz = nx * inv, ny * inv, nz * inv
        cos = abs(nx * dx + ny * dy + nz * dz)
        eps = 1e-7 * (1.0 + max(abs(hx), max(abs(hy), abs(hz))))  # geometry.offset_origin's
        base = s + eps / max(cos, MIN_COS)
        if base >= tmax:
            return np.inf, -1
        sx, sy, sz = ox + base * dx, oy + base * dy, oz + base * dz
        passed = prim
        t, prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                                   stack, sx, sy, sz, dx, dy, dz, tmax - base, False)
    if prim < 0:
        return np.inf, -1
    return base + t, prim


@kernel_inline
def trace(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """The closest hit before tmax that the masks keep: (t, prim) or (inf, -1)."""
    t, prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                               stack, ox, oy, oz, dx, dy, dz, tmax, False)
    if prim >= 0 and masked(sc, prim):
        t, prim = pass_masks(sc, stack, ox, oy, oz, dx, dy, dz, tmax, t, prim)
    return t, prim


@kernel
def blocked_after_masks(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """`blocked` past an any-hit that found a masked surface: nearest hit first."""
    t, prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                               stack, ox, oy, oz, dx, dy, dz, tmax, False)
    return pass_masks(sc, stack, ox, oy, oz, dx, dy, dz, tmax, t, prim)[1] >= 0


@kernel_inline
def blocked(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """True if a surface the masks keep lies along the ray in (0, tmax)."""
    prim = intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                            stack, ox, oy, oz, dx, dy, dz, tmax, True)[1]
    if prim >= 0 and masked(sc, prim):
        return blocked_after_masks(sc, stack, ox, oy, oz, dx, dy, dz, tmax)
    return prim >= 0
