"""Ray-primitive intersection and BVH traversal.

Rays are (origin, direction) as six floats; a hit is the distance `t` and
the primitive id (triangles first, then spheres; see scene.py). Callers
offset ray origins off the surface (`offset_origin`) instead of skipping
the primitive they left, so refraction through a sphere still finds the
sphere's far side.
"""

import math

import numpy as np

from . import kernel

STACK_SIZE = 64


@kernel
def tri_hit(tri_p, i, ox, oy, oz, dx, dy, dz, tmax):
    """Moller-Trumbore; returns t in (0, tmax) or -1."""
    ax, ay, az = tri_p[i, 0, 0], tri_p[i, 0, 1], tri_p[i, 0, 2]
    e1x, e1y, e1z = tri_p[i, 1, 0] - ax, tri_p[i, 1, 1] - ay, tri_p[i, 1, 2] - az
    e2x, e2y, e2z = tri_p[i, 2, 0] - ax, tri_p[i, 2, 1] - ay, tri_p[i, 2, 2] - az
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return -1.0
    inv = 1.0 / det
    tx, ty, tz = ox - ax, oy - ay, oz - az
    u = (tx * px + ty * py + tz * pz) * inv
    if u < 0.0 or u > 1.0:
        return -1.0
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return -1.0
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if t <= 0.0 or t >= tmax:
        return -1.0
    return t


@kernel
def sphere_hit(sph, i, ox, oy, oz, dx, dy, dz, tmax):
    """Nearest t in (0, tmax) where the ray meets sphere i, or -1.
    Uses the stable form b' = d.(o-c), discriminant from |o-c - (d.(o-c))d|."""
    cx, cy, cz, r = sph[i, 0], sph[i, 1], sph[i, 2], sph[i, 3]
    fx, fy, fz = ox - cx, oy - cy, oz - cz
    a = dx * dx + dy * dy + dz * dz
    b = fx * dx + fy * dy + fz * dz
    # |f - (b/a) d|^2 is accurate even far from the sphere (Ray Tracing Gems ch. 7)
    lx, ly, lz = fx - b / a * dx, fy - b / a * dy, fz - b / a * dz
    disc = a * (r * r - (lx * lx + ly * ly + lz * lz))
    if disc < 0.0:
        return -1.0
    sq = math.sqrt(disc)
    q = -(b + math.copysign(sq, b))
    c = fx * fx + fy * fy + fz * fz - r * r
    t0 = c / q if q != 0.0 else 0.0
    t1 = q / a
    if t0 > t1:
        t0, t1 = t1, t0
    if 0.0 < t0 < tmax:
        return t0
    if 0.0 < t1 < tmax:
        return t1
    return -1.0


@kernel
def _prim_hit(tri_p, sph, prim, ox, oy, oz, dx, dy, dz, tmax):
    n_tri = tri_p.shape[0]
    if prim < n_tri:
        return tri_hit(tri_p, prim, ox, oy, oz, dx, dy, dz, tmax)
    return sphere_hit(sph, prim - n_tri, ox, oy, oz, dx, dy, dz, tmax)


@kernel
def _box_hit(bmin, bmax, node, ox, oy, oz, ix, iy, iz, tmax):
    t0x = (bmin[node, 0] - ox) * ix
    t1x = (bmax[node, 0] - ox) * ix
    t0y = (bmin[node, 1] - oy) * iy
    t1y = (bmax[node, 1] - oy) * iy
    t0z = (bmin[node, 2] - oz) * iz
    t1z = (bmax[node, 2] - oz) * iz
    lo = max(max(min(t0x, t1x), min(t0y, t1y)), max(min(t0z, t1z), 0.0))
    hi = min(min(max(t0x, t1x), max(t0y, t1y)), min(max(t0z, t1z), tmax))
    # widened by 2 ulps so a ray grazing a flat box (zero thickness) still enters
    return lo <= hi * 1.0000000000000004


@kernel
def intersect(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """Closest hit along the ray before tmax: (t, prim) or (inf, -1)."""
    return intersect_arrays(sc.bvh_min, sc.bvh_max, sc.bvh_info, sc.bvh_prims, sc.tri_p, sc.sph,
                            stack, ox, oy, oz, dx, dy, dz, tmax)


# Hot loops call the *_arrays forms with the arrays they need: passing the
# whole SceneArrays tuple into a non-inlined call copies every array struct.
@kernel
def intersect_arrays(bmin, bmax, info, prims, tri_p, sph, stack, ox, oy, oz, dx, dy, dz, tmax):
    ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / dz
    best_t = tmax
    best = -1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if not _box_hit(bmin, bmax, node, ox, oy, oz, ix, iy, iz, best_t):
            continue
        axis = info[node, 2]
        if axis < 0:
            first = info[node, 0]
            for k in range(first, first + info[node, 1]):
                prim = prims[k]
                t = _prim_hit(tri_p, sph, prim, ox, oy, oz, dx, dy, dz, best_t)
                if t > 0.0:
                    best_t = t
                    best = prim
        else:
            left = node + 1
            right = info[node, 0]
            neg = (dx < 0.0) if axis == 0 else ((dy < 0.0) if axis == 1 else (dz < 0.0))
            if neg:  # visit the right (far-coordinate) child first
                stack[sp] = left
                stack[sp + 1] = right
            else:
                stack[sp] = right
                stack[sp + 1] = left
            sp += 2
    if best < 0:
        return np.inf, -1
    return best_t, best


@kernel
def occluded(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """True if anything lies along the ray in (0, tmax): a shadow ray."""
    return occluded_arrays(sc.bvh_min, sc.bvh_max, sc.bvh_info, sc.bvh_prims, sc.tri_p, sc.sph,
                           stack, ox, oy, oz, dx, dy, dz, tmax)


@kernel
def occluded_arrays(bmin, bmax, info, prims, tri_p, sph, stack, ox, oy, oz, dx, dy, dz, tmax):
    ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / dz
    sp = 1
    stack[0] = 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if not _box_hit(bmin, bmax, node, ox, oy, oz, ix, iy, iz, tmax):
            continue
        if info[node, 2] < 0:
            first = info[node, 0]
            for k in range(first, first + info[node, 1]):
                if _prim_hit(tri_p, sph, prims[k], ox, oy, oz, dx, dy, dz, tmax) > 0.0:
                    return True
        else:
            stack[sp] = node + 1
            stack[sp + 1] = info[node, 0]
            sp += 2
    return False


@kernel
def surface_at(sc, prim, px, py, pz):
    """(front normal xyz, material, light) of primitive `prim` at a point on it.
    The front side is the side a one-sided material reflects on and an area
    light emits from."""
    return surface_at_arrays(sc.tri_n, sc.tri_mat, sc.tri_light, sc.sph, sc.sph_flip, sc.sph_mat,
                             sc.sph_light, prim, px, py, pz)


@kernel
def surface_at_arrays(tri_n, tri_mat, tri_light, sph, sph_flip, sph_mat, sph_light, prim,
                      px, py, pz):
    n_tri = tri_n.shape[0]
    if prim < n_tri:
        return tri_n[prim, 0], tri_n[prim, 1], tri_n[prim, 2], tri_mat[prim], tri_light[prim]
    s = prim - n_tri
    inv_r = 1.0 / sph[s, 3]
    if sph_flip[s] != 0:
        inv_r = -inv_r
    return ((px - sph[s, 0]) * inv_r, (py - sph[s, 1]) * inv_r, (pz - sph[s, 2]) * inv_r,
            sph_mat[s], sph_light[s])


@kernel
def offset_origin(px, py, pz, nx, ny, nz, side):
    """Move a point off its surface along the normal, to the side `side`
    (+1 along n, -1 against it) so the spawned ray does not re-hit it."""
    eps = 1e-7 * (1.0 + max(abs(px), max(abs(py), abs(pz))))
    return px + side * eps * nx, py + side * eps * ny, pz + side * eps * nz
