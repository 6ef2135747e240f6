"""A bounding volume hierarchy built with the surface area heuristic.

Binned SAH (16 bins per axis, as in pbrt-v4's BVHAggregate) over primitive
bounds builds a binary tree: nodes are stored depth-first, so an inner
node's left child is the next node and `info[node, 0]` is its right child.
Leaves hold at most MAX_LEAF primitives. Below MAX_SAH_DEPTH the split is the
median, which bounds the depth (and so the traversal stack).

The renderer traverses the 4-wide tree `collapse_wide` makes of it (kernels/
geometry.intersect_arrays): measured with bench/traversal.py and whole
renders, the wide tree renders 12 % more samples/s on cornell-box, 5 % on
veach-mis and 20 % on a 100 k-triangle mesh (bench/heavy_mesh.py). Float32
boxes (rounded outwards, half the bytes) were slower on all three: the
conversions cost more than the memory they save at these sizes. Tested in
float32 as well (2026-11-27, kernels/packet.py's docstring), they gained
packets at most 11 %, on camera rays, and cost shadow rays.

Tried and not kept (2026-11-26, AVX-512 machine, bench/traversal.py's rays):
8-wide nodes whose eight slab tests are one loop Numba's loop vectorizer
turns into zmm instructions, with leaves of up to 8 triangles in padded
structure-of-arrays slots tested branch-free in one vector pass (the same
hits, bit for bit). Against this 4-wide scalar traversal: cornell-box
camera / bounce / shadow rays 0.97x / 1.19x / 1.32x, veach-mis 0.81x /
1.11x / 0.91x, the 100 k-triangle mesh 0.89x / 0.96x / 1.03x. A single ray
keeps too little work per node for the vector units to pay for the spills
and the per-node selection that follows; packets of rays are what vectorize
(Mitsuba's LLVM backend traces 16 rays per instruction): the path tracer
traces packets of 16 (kernels/packet.py), the other methods single rays.

TRAVERSAL_COST is 2, not pbrt's 1/8: in these scalar Numba kernels a node's
slab test costs about as much as a triangle test, and on cornell-box the
shallower tree (31 nodes instead of 43) rendered ~20 % more samples/s.
Measured again with the path tracer's packets (2026-11-28, AMD EPYC Zen 4,
128x128, 64 spp, one thread, six interleaved pairs of processes, the same
film bytes): TRAVERSAL_COST 1, cornell-box -1.3 %, veach-mis +0.1 % time;
0.5, -0.4 % and -0.8 %; MAX_LEAF 2, cornell-box -0.5 %. All within about
the noise, so the costs stay as they are.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .kernels.geometry import STACK_SIZE

__all__ = ["build_bvh", "collapse_wide", "wide_bounds"]

N_BINS = 16
MAX_LEAF = 4
TRAVERSAL_COST = 2.0  # relative to one primitive test (see module doc)
# Below this depth of the binary tree, median splits (see _build): with at
# most 5 M primitives (scene_format.MAX_TRIANGLES; spheres count too, but a
# scene that large is refused first) the tree is at most 32 + 23 = 55 deep.
MAX_SAH_DEPTH = 32


@njit(cache=True)
def _area(lo0, lo1, lo2, hi0, hi1, hi2):
    dx, dy, dz = hi0 - lo0, hi1 - lo1, hi2 - lo2
    if dx < 0.0:
        return 0.0
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@njit(cache=True)
def _build(lo, hi, prims):
    n = prims.shape[0]
    max_nodes = max(2 * n, 1)
    node_min = np.zeros((max_nodes, 3))
    node_max = np.zeros((max_nodes, 3))
    info = np.zeros((max_nodes, 3), np.int32)
    order = prims.copy()
    cen = 0.5 * (lo + hi)
    # job stack: (start, end, parent or -1, depth)
    stack = np.zeros((128, 4), np.int64)
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = 0, n, -1, 0
    sp = 1
    n_nodes = 0
    bin_lo = np.zeros((N_BINS, 3))
    bin_hi = np.zeros((N_BINS, 3))
    bin_n = np.zeros(N_BINS, np.int64)
    right_area = np.zeros(N_BINS)
    right_n = np.zeros(N_BINS, np.int64)
    while sp > 0:
        sp -= 1
        start, end, parent, depth = stack[sp, 0], stack[sp, 1], stack[sp, 2], stack[sp, 3]
        node = n_nodes
        n_nodes += 1
        if parent >= 0:
            info[parent, 0] = node  # this job is always the parent's right child
        bmin = np.full(3, np.inf)
        bmax = np.full(3, -np.inf)
        cmin = np.full(3, np.inf)
        cmax = np.full(3, -np.inf)
        for i in range(start, end):
            p = order[i]
            for k in range(3):
                bmin[k] = min(bmin[k], lo[p, k])
                bmax[k] = max(bmax[k], hi[p, k])
                cmin[k] = min(cmin[k], cen[p, k])
                cmax[k] = max(cmax[k], cen[p, k])
        for k in range(3):
            node_min[node, k] = bmin[k]
            node_max[node, k] = bmax[k]
        count = end - start
        best_axis, best_bin, best_cost = -1, -1, np.inf
        if count > 1:
            parent_area = _area(bmin[0], bmin[1], bmin[2], bmax[0], bmax[1], bmax[2])
            for axis in range(3):
                extent = cmax[axis] - cmin[axis]
                if extent <= 0.0:
                    continue
                bin_n[:] = 0
                bin_lo[:, :] = np.inf
                bin_hi[:, :] = -np.inf
                for i in range(start, end):
                    p = order[i]
                    b = int(N_BINS * (cen[p, axis] - cmin[axis]) / extent)
                    b = min(max(b, 0), N_BINS - 1)
                    bin_n[b] += 1
                    for k in range(3):
                        bin_lo[b, k] = min(bin_lo[b, k], lo[p, k])
                        bin_hi[b, k] = max(bin_hi[b, k], hi[p, k])
                # sweep from the right: area and count of bins b..N-1
                rl = np.full(3, np.inf)
                rh = np.full(3, -np.inf)
                rn = 0
                for b in range(N_BINS - 1, 0, -1):
                    rn += bin_n[b]
                    for k in range(3):
                        rl[k] = min(rl[k], bin_lo[b, k])
                        rh[k] = max(rh[k], bin_hi[b, k])
                    right_n[b] = rn
                    right_area[b] = _area(rl[0], rl[1], rl[2], rh[0], rh[1], rh[2]) if rn > 0 else 0.0
                ll = np.full(3, np.inf)
                lh = np.full(3, -np.inf)
                ln = 0
                for b in range(0, N_BINS - 1):
                    ln += bin_n[b]
                    for k in range(3):
                        ll[k] = min(ll[k], bin_lo[b, k])
                        lh[k] = max(lh[k], bin_hi[b, k])
                    if ln == 0 or right_n[b + 1] == 0:
                        continue
                    la = _area(ll[0], ll[1], ll[2], lh[0], lh[1], lh[2])
                    cost = TRAVERSAL_COST + (la * ln + right_area[b + 1] * right_n[b + 1]) / max(parent_area, 1e-300)
                    if cost < best_cost:
                        best_cost, best_axis, best_bin = cost, axis, b
        make_leaf = best_axis < 0 or (count <= MAX_LEAF and best_cost >= count)
        if count > MAX_LEAF and depth >= MAX_SAH_DEPTH:
            # deep enough: split at the median centroid of the widest axis, so
            # the subtree is balanced (at most log2(count) more levels)
            axis = int(np.argmax(cmax - cmin))
            sub = order[start:end].copy()
            order[start:end] = sub[np.argsort(cen[sub, axis], kind="mergesort")]
            mid = start + count // 2
            best_axis = axis
        elif make_leaf and count > MAX_LEAF and best_axis < 0:
            # all centroids coincide: split in the middle of the list
            mid = start + count // 2
        elif make_leaf:
            mid = -1
        else:
            extent = cmax[best_axis] - cmin[best_axis]
            i, j = start, end - 1
            while i <= j:
                b = int(N_BINS * (cen[order[i], best_axis] - cmin[best_axis]) / extent)
                b = min(max(b, 0), N_BINS - 1)
                if b <= best_bin:
                    i += 1
                else:
                    tmp = order[i]
                    order[i] = order[j]
                    order[j] = tmp
                    j -= 1
            mid = i
            if mid == start or mid == end:
                mid = start + count // 2
        if mid < 0:
            info[node, 0] = start
            info[node, 1] = count
            info[node, 2] = -1
            continue
        info[node, 1] = 0
        info[node, 2] = best_axis if best_axis >= 0 else 0
        if sp + 2 > stack.shape[0]:
            bigger = np.zeros((stack.shape[0] * 2, 4), np.int64)
            bigger[:sp] = stack[:sp]
            stack = bigger
        # push right first so the left child is built next (node + 1)
        stack[sp, 0], stack[sp, 1], stack[sp, 2], stack[sp, 3] = mid, end, node, depth + 1
        sp += 1
        stack[sp, 0], stack[sp, 1], stack[sp, 2], stack[sp, 3] = start, mid, -1, depth + 1
        sp += 1
    return node_min[:n_nodes].copy(), node_max[:n_nodes].copy(), info[:n_nodes].copy(), order


def build_bvh(lo: np.ndarray, hi: np.ndarray, prim_ids: np.ndarray):
    """Build over the bounds of `prim_ids` -> (node_min, node_max, info, prims)."""
    if len(prim_ids) == 0:  # an empty scene still needs a root: an empty leaf
        return (np.full((1, 3), np.inf), np.full((1, 3), -np.inf),
                np.array([[0, 0, -1]], np.int32), np.zeros(0, np.int32))
    return _build(np.ascontiguousarray(lo, dtype=np.float64),
                  np.ascontiguousarray(hi, dtype=np.float64), prim_ids.astype(np.int32))


WIDTH = 4  # children per node of the wide BVH


@njit(cache=True)
def _surface(node_min, node_max, n):
    dx = max(node_max[n, 0] - node_min[n, 0], 0.0)
    dy = max(node_max[n, 1] - node_min[n, 1], 0.0)
    dz = max(node_max[n, 2] - node_min[n, 2], 0.0)
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@njit(cache=True)
def _collapse(node_min, node_max, info):
    """collapse_wide's loop: (boxes, kids, wide nodes made, deepest level)."""
    n_bin = info.shape[0]
    boxes = np.empty((n_bin, 24))  # a wide node per binary inner node at most
    kids = np.full((n_bin, WIDTH), -1, np.int32)  # -1: an empty leaf
    queue = np.empty(n_bin, np.int64)  # binary nodes that become wide nodes; position = index
    depth = np.empty(n_bin, np.int64)
    queue[0], depth[0] = 0, 1
    tail = 1
    max_depth = 1
    lanes = np.empty(WIDTH, np.int64)
    root_is_leaf = info[0, 2] < 0
    for head in range(n_bin):
        if head == tail:
            break
        n = queue[head]
        max_depth = max(max_depth, depth[head])
        if root_is_leaf:
            lanes[0], m = n, 1
        else:
            lanes[0], lanes[1], m = n + 1, info[n, 0], 2
        while m < WIDTH:  # open the inner lane with the largest area (the first of equals)
            widest, area = -1, -1.0
            for k in range(m):
                if info[lanes[k], 2] >= 0:
                    a = _surface(node_min, node_max, lanes[k])
                    if a > area:
                        widest, area = k, a
            if widest < 0:
                break
            c = lanes[widest]
            for k in range(m, widest + 1, -1):
                lanes[k] = lanes[k - 1]
            lanes[widest], lanes[widest + 1] = c + 1, info[c, 0]
            m += 1
        boxes[head, 0:12] = np.inf
        boxes[head, 12:24] = -np.inf
        for k in range(m):
            c = lanes[k]
            for a in range(3):
                boxes[head, 4 * a + k] = node_min[c, a]
                boxes[head, 12 + 4 * a + k] = node_max[c, a]
            if info[c, 2] < 0:
                kids[head, k] = -(info[c, 0] * 8 + info[c, 1]) - 1  # count <= MAX_LEAF < 8
            else:
                kids[head, k] = tail
                queue[tail], depth[tail] = c, depth[head] + 1
                tail += 1
    return boxes, kids, tail, max_depth


def collapse_wide(node_min, node_max, info):
    """The binary BVH as a 4-wide one -> (boxes (M, 24) float64, kids (M, 4) int32).

    Each wide node keeps up to four grandchildren of the binary tree: starting
    from the two children, the inner child with the largest surface area is
    replaced by its own two children until there are four (as Embree's and
    pbrt's wide BVHs collapse a binary SAH tree). Row layout, lane k = 0..3:
    boxes [lo_x k, lo_y k, lo_z k, hi_x k, hi_y k, hi_z k] at columns 4 c + k
    for c = 0..5 (one coordinate's four lanes side by side, so a slab test of
    the four children reads contiguous memory); kids [item k]: a wide node's
    index (>= 0), or a leaf, -(first * 8 + count) - 1 over bvh_prims (count
    <= MAX_LEAF < 8). Empty lanes are empty leaves (-1) in an empty box
    (lo = +inf, hi = -inf) that no ray enters. Wide nodes are numbered
    breadth-first.
    """
    boxes, kids, n_wide, max_depth = _collapse(np.ascontiguousarray(node_min, dtype=np.float64),
                                               np.ascontiguousarray(node_max, dtype=np.float64),
                                               info)
    # what intersect_arrays' stack must hold (see STACK_SIZE): MAX_SAH_DEPTH
    # guarantees it, this says so if that ever changes
    if 3 * max_depth + 1 > STACK_SIZE:
        raise RuntimeError(f"BVH {max_depth} levels deep: traversal stack too small")
    return boxes[:n_wide].copy(), kids[:n_wide].copy()


def wide_bounds(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scene's bounding box (lo xyz, hi xyz) from the wide root's lanes."""
    return boxes[0, 0:12].reshape(3, 4).min(axis=1), boxes[0, 12:24].reshape(3, 4).max(axis=1)
