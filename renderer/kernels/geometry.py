"""Ray-primitive intersection and BVH traversal.

Rays are (origin, direction) as six floats; a hit is the distance `t` and
the primitive id (triangles first, then spheres; see scene.py). Callers
offset ray origins off the surface (`offset_origin`) instead of skipping
the primitive they left, so refraction through a sphere still finds the
sphere's far side.
"""

import math

import numpy as np

from . import kernel, kernel_inline

# The wide traversal keeps at most 3 entries per level of the tree (plus the
# node being visited); bvh.py bounds the binary tree's depth by 55, and a
# wide tree is never deeper than the binary one it collapses.
STACK_SIZE = 3 * 55 + 1
BARY_EPS = 1e-12


@kernel_inline
def tri_hit(tri, i, ox, oy, oz, dx, dy, dz, tmax):
    """Moller-Trumbore against row i of `tri_isect` (v0, e1, e2); t in (0, tmax) or -1."""
    ax, ay, az = tri[i, 0], tri[i, 1], tri[i, 2]
    e1x, e1y, e1z = tri[i, 3], tri[i, 4], tri[i, 5]
    e2x, e2y, e2z = tri[i, 6], tri[i, 7], tri[i, 8]
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return -1.0
    inv = 1.0 / det
    tx, ty, tz = ox - ax, oy - ay, oz - az
    u = (tx * px + ty * py + tz * pz) * inv
    # BARY_EPS widens every triangle by a hair so a ray through an edge two
    # triangles share (or a box corner) cannot slip between them by rounding
    if u < -BARY_EPS or u > 1.0 + BARY_EPS:
        return -1.0
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < -BARY_EPS or u + v > 1.0 + BARY_EPS:
        return -1.0
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if t <= 0.0 or t >= tmax:
        return -1.0
    return t


@kernel_inline
def sphere_t(cx, cy, cz, r, ox, oy, oz, dx, dy, dz, tmax):
    """(t, hit): the nearest t in (0, tmax) where the ray meets the sphere
    with centre c and radius r, and whether it does. Uses the stable form
    b' = d.(o-c), discriminant from |o-c - (d.(o-c))d|.

    Without a branch (the early miss and the choice of the two distances
    are selects), so that the packet's loop over its lanes, which calls it
    for every lane (kernels/packet.py), vectorizes; `sphere_hit` is this
    for one ray. The square root of a negative discriminant is taken of 0
    instead, and the lane's `hit` says it missed."""
    fx, fy, fz = ox - cx, oy - cy, oz - cz
    a = dx * dx + dy * dy + dz * dz
    b = fx * dx + fy * dy + fz * dz
    # |f - (b/a) d|^2 is accurate even far from the sphere (Ray Tracing Gems ch. 7)
    lx, ly, lz = fx - b / a * dx, fy - b / a * dy, fz - b / a * dz
    disc = a * (r * r - (lx * lx + ly * ly + lz * lz))
    sq = math.sqrt(disc if disc >= 0.0 else 0.0)
    q = -(b + math.copysign(sq, b))
    c = fx * fx + fy * fy + fz * fz - r * r
    t0 = c / q if q != 0.0 else 0.0
    t1 = q / a
    lo = t1 if t0 > t1 else t0
    hi = t0 if t0 > t1 else t1
    t = lo if (0.0 < lo) & (lo < tmax) else hi
    return t, (disc >= 0.0) & (0.0 < t) & (t < tmax)


@kernel
def sphere_hit(sph, i, ox, oy, oz, dx, dy, dz, tmax):
    """Nearest t in (0, tmax) where the ray meets sphere i, or -1 (`sphere_t`)."""
    t, hit = sphere_t(sph[i, 0], sph[i, 1], sph[i, 2], sph[i, 3], ox, oy, oz, dx, dy, dz, tmax)
    return t if hit else -1.0
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


@kernel_inline
def _prim_hit(tri, sph, prim, ox, oy, oz, dx, dy, dz, tmax):
    n_tri = tri.shape[0]
    if prim < n_tri:
        return tri_hit(tri, prim, ox, oy, oz, dx, dy, dz, tmax)
    return sphere_hit(sph, prim - n_tri, ox, oy, oz, dx, dy, dz, tmax)


@kernel_inline
def _fmin(a, b):
    return a if a < b else b


@kernel_inline
def _fmax(a, b):
    return a if a > b else b


@kernel
def intersect(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """Closest hit along the ray before tmax: (t, prim) or (inf, -1)."""
    return intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                            stack, ox, oy, oz, dx, dy, dz, tmax, False)


@kernel
def occluded(sc, stack, ox, oy, oz, dx, dy, dz, tmax):
    """True if anything lies along the ray in (0, tmax): a shadow ray."""
    return intersect_arrays(sc.bvh_nodes, sc.bvh_info, sc.bvh_prims, sc.tri_isect, sc.sph,
                            stack, ox, oy, oz, dx, dy, dz, tmax, True)[1] >= 0


@kernel_inline
def _lane(b, node, k, cx0, cy0, cz0, cx1, cy1, cz1, ix, iy, iz, oix, oiy, oiz, best_t):
    """Entry distance of the ray into lane k's box of wide node `node`, or inf."""
    lo = _fmax(_fmax(b[node, cx0 + k] * ix - oix, b[node, cy0 + k] * iy - oiy),
               _fmax(b[node, cz0 + k] * iz - oiz, 0.0))
    hi = _fmin(_fmin(b[node, cx1 + k] * ix - oix, b[node, cy1 + k] * iy - oiy),
               _fmin(b[node, cz1 + k] * iz - oiz, best_t))
    return lo if lo <= hi * 1.0000000000000004 else np.inf


# Hot loops call intersect_arrays with the arrays it needs: passing the whole
# SceneArrays tuple into a non-inlined call copies every array struct.
@kernel
def intersect_arrays(boxes, kids, prims, tri, sph, stack, ox, oy, oz, dx, dy, dz, tmax, any_hit):
    """BVH traversal: the closest hit (t, prim) before tmax, or (inf, -1);
    with `any_hit`, stop at the first hit found (shadow rays).

    The BVH is 4-wide (bvh.collapse_wide): a node's four child boxes are
    slab-tested together, t = bound / d - o / d with the near and far bound
    columns chosen once per ray from the direction's signs, and the children
    hit are visited nearest first (the nearest at once, the others pushed
    farthest first). Against the binary tree it is collapsed from, in these
    scalar kernels (Numba leaves SLP vectorization off, so the four slab
    tests are four scalar ones): 12 % more samples/s on cornell-box, 5 % on
    veach-mis, 20 % on a 100 k-triangle mesh (bench/traversal.py). `stack`
    holds at most 3 entries per level (STACK_SIZE).
    """
    ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / dz
    oix, oiy, oiz = ox * ix, oy * iy, oz * iz
    cx0 = 12 if dx < 0.0 else 0
    cy0 = 16 if dy < 0.0 else 4
    cz0 = 20 if dz < 0.0 else 8
    cx1, cy1, cz1 = 12 - cx0, 20 - cy0, 28 - cz0
    best_t = tmax
    best = -1
    item = 0  # the root
    sp = 0
    while True:
        if item < 0:
            code = -item - 1
            first = code >> 3
            for k in range(first, first + (code & 7)):
                prim = prims[k]
                t = _prim_hit(tri, sph, prim, ox, oy, oz, dx, dy, dz, best_t)
                if t > 0.0:
                    best_t = t
                    best = prim
                    if any_hit:
                        return best_t, best
            if sp == 0:
                break
            sp -= 1
            item = stack[sp]
            continue
        t0 = _lane(boxes, item, 0, cx0, cy0, cz0, cx1, cy1, cz1, ix, iy, iz, oix, oiy, oiz, best_t)
        t1 = _lane(boxes, item, 1, cx0, cy0, cz0, cx1, cy1, cz1, ix, iy, iz, oix, oiy, oiz, best_t)
        t2 = _lane(boxes, item, 2, cx0, cy0, cz0, cx1, cy1, cz1, ix, iy, iz, oix, oiy, oiz, best_t)
        t3 = _lane(boxes, item, 3, cx0, cy0, cz0, cx1, cy1, cz1, ix, iy, iz, oix, oiy, oiz, best_t)
        k0, k1, k2, k3 = kids[item, 0], kids[item, 1], kids[item, 2], kids[item, 3]
        # sort the four lanes by entry distance (a 5-comparator network); go
        # on to the nearest hit and push the others farthest first
        if t1 < t0:
            t0, t1, k0, k1 = t1, t0, k1, k0
        if t3 < t2:
            t2, t3, k2, k3 = t3, t2, k3, k2
        if t2 < t0:
            t0, t2, k0, k2 = t2, t0, k2, k0
        if t3 < t1:
            t1, t3, k1, k3 = t3, t1, k3, k1
        if t2 < t1:
            t1, t2, k1, k2 = t2, t1, k2, k1
        if t0 == np.inf:  # no child hit
            if sp == 0:
                break
            sp -= 1
            item = stack[sp]
            continue
        if t3 < np.inf:
            stack[sp] = k3
            sp += 1
        if t2 < np.inf:
            stack[sp] = k2
            sp += 1
        if t1 < np.inf:
            stack[sp] = k1
            sp += 1
        item = k0
    if best < 0:
        return np.inf, -1
    return best_t, best


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


@kernel
def shadow_ray(hx, hy, hz, nx, ny, nz, wx, wy, wz, dist):
    """A shadow ray from the offset origin to the light point q = h + dist w:
    (origin, unit direction, tmax). Distance and direction are measured from
    the *offset* origin, and tmax stops a relative 1e-9 short of q, so the
    light's own surface never shadows its sample (with dist from h, a 2e-7
    offset towards an overhead light made q itself an occluder)."""
    qx, qy, qz = hx + dist * wx, hy + dist * wy, hz + dist * wz
    sx, sy, sz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
    dx, dy, dz = qx - sx, qy - sy, qz - sz
    d = np.sqrt(dx * dx + dy * dy + dz * dz)
    inv = 1.0 / d
    return sx, sy, sz, dx * inv, dy * inv, dz * inv, d * (1.0 - 1e-9)
