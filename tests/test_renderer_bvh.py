"""The BVH against the obvious answer: every primitive tested in turn."""

import numpy as np
import pytest

from renderer import build_scene, load_scene, resolve_document
from renderer.kernels.geometry import STACK_SIZE, _prim_hit, intersect, occluded


def brute_force(arrays, o, d, tmax=np.inf):
    best_t, best = tmax, -1
    for prim in range(arrays.tri_isect.shape[0] + arrays.sph.shape[0]):
        t = _prim_hit(arrays.tri_isect, arrays.sph, prim, *o, *d, best_t)
        if t > 0:
            best_t, best = t, prim
    return (best_t, best) if best >= 0 else (np.inf, -1)


def random_soup(rng, n_tri=300, n_sph=20):
    v = rng.uniform(-5, 5, (n_tri, 3))[:, None, :] + rng.normal(0, 0.7, (n_tri, 3, 3))
    shapes = [{"type": "mesh", "material": "m", "vertices": v.reshape(-1, 3).tolist(),
               "faces": np.arange(3 * n_tri).reshape(-1, 3).tolist()}]
    for c, r in zip(rng.uniform(-5, 5, (n_sph, 3)), rng.uniform(0.1, 1.0, n_sph)):
        shapes.append({"type": "sphere", "material": "m", "center": c.tolist(), "radius": float(r)})
    return build_scene(resolve_document({
        "camera": {"origin": [0, 0, 20], "target": [0, 0, 0], "fov": 40},
        "materials": {"m": {"type": "diffuse"}}, "shapes": shapes})).arrays


@pytest.mark.parametrize("scene", ["cornell-box", "soup"])
def test01_closest_hit_and_any_hit_agree_with_brute_force(scene):
    rng = np.random.default_rng(5)
    arrays = random_soup(rng) if scene == "soup" else load_scene(scene).arrays
    stack = np.empty(STACK_SIZE, np.int64)
    hits = 0
    for _ in range(3000):
        o = rng.uniform(-6, 6, 3) if scene == "soup" else rng.uniform(-0.99, 0.99, 3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        if rng.random() < 0.05:  # axis-aligned rays: zero direction components
            d = np.zeros(3)
            d[rng.integers(3)] = rng.choice([-1.0, 1.0])
        t, prim = intersect(arrays, stack, *o, *d, np.inf)
        bt, bprim = brute_force(arrays, o, d)
        assert t == bt
        # coplanar surfaces (the small box's bottom lies on the floor) tie exactly
        assert prim == bprim or _prim_hit(arrays.tri_isect, arrays.sph, prim, *o, *d, np.inf) == t
        if prim >= 0:
            hits += 1
            assert occluded(arrays, stack, *o, *d, t * 1.0001)
            assert not occluded(arrays, stack, *o, *d, t * 0.9999)
    assert hits > 500


def binary_depth(info: np.ndarray) -> int:
    """Levels of a binary BVH from build_bvh (inner: [right, 0, axis], left = node + 1)."""
    depth, todo = 0, [(0, 1)]
    while todo:
        n, d = todo.pop()
        depth = max(depth, d)
        if info[n, 2] >= 0:
            todo += [(n + 1, d + 1), (int(info[n, 0]), d + 1)]
    return depth


def wide_depth(kids: np.ndarray) -> int:
    """Levels of the wide BVH (children >= 0 are nodes, < 0 leaves)."""
    depth, level = 0, [0]
    while level:
        depth += 1
        level = [int(c) for n in level for c in kids[n] if c >= 0]
    return depth


def test02_a_scene_that_drives_sah_deep_stays_within_the_traversal_stack():
    """Triangles twice as large and twice as far at each step: SAH cuts off
    one or two at a time, so the tree would be about as deep as there are
    triangles. The builder switches to median splits at depth
    bvh.MAX_SAH_DEPTH, so the traversal stack (3 entries per level) cannot
    overflow, and traversal still finds what brute force finds."""
    from renderer.bvh import MAX_SAH_DEPTH, build_bvh

    n = 100
    x = 1e-24 * 2.0 ** np.arange(n)  # up to 6e5: within MAX_COORDINATE
    s = 0.2 * x
    v = np.stack([np.stack([x, np.zeros(n), np.zeros(n)], 1),
                  np.stack([x + s, np.zeros(n), s], 1),
                  np.stack([x, s, s], 1)], 1)
    arrays = build_scene(resolve_document({
        "camera": {"origin": [0, 0, 20], "target": [0, 0, 0], "fov": 40},
        "materials": {"m": {"type": "diffuse"}},
        "shapes": [{"type": "mesh", "material": "m", "vertices": v.reshape(-1, 3).tolist(),
                    "faces": np.arange(3 * n).reshape(-1, 3).tolist()}]})).arrays
    tri = v.reshape(n, 3, 3)
    info = build_bvh(tri.min(axis=1), tri.max(axis=1), np.arange(n, dtype=np.int32))[2]
    assert MAX_SAH_DEPTH < binary_depth(info) <= 55  # SAH went deep; median splits from there
    depth = wide_depth(arrays.bvh_info)
    assert 3 * depth + 1 <= STACK_SIZE
    rng = np.random.default_rng(3)
    stack = np.full(STACK_SIZE + 8, -7, np.int64)
    for _ in range(1500):
        i = rng.integers(n)
        target = v[i].mean(axis=0) + rng.normal(0, 0.3, 3) * s[i]
        o = target + rng.normal(0, 1, 3) * 5 * x[i]  # at the triangle's own scale
        d = (target - o) / np.linalg.norm(target - o)
        t, prim = intersect(arrays, stack, *o, *d, np.inf)
        assert (t, prim) == brute_force(arrays, o, d)
    assert np.all(stack[STACK_SIZE:] == -7)  # nothing written past the stack


def trace_packets(arrays, origins, dirs, tmax, any_hit, active, stack):
    """kernels.packet over the rays in packets of PACKET: (t, prim, act) per ray."""
    from renderer.kernels.packet import PACKET, packet_intersect

    n = len(origins)
    t_out, p_out, a_out = np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64)
    lanes = np.zeros((10, PACKET))
    for base in range(0, n, PACKET):
        m = min(PACKET, n - base)
        lanes[:] = 1.0
        lanes[0:3, :m], lanes[3:6, :m] = origins[base:base + m].T, dirs[base:base + m].T
        lanes[9, :m] = tmax[base:base + m]
        act = np.zeros(PACKET, np.int64)
        act[:m] = active[base:base + m]
        bp = np.full(PACKET, 99, np.int64)
        packet_intersect(arrays.bvh_nodes, arrays.bvh_info, arrays.bvh_prims, arrays.tri_isect,
                         arrays.sph, stack, *lanes, bp, act, any_hit)
        t_out[base:base + m], p_out[base:base + m] = lanes[9, :m], bp[:m]
        a_out[base:base + m] = act[:m]
    return t_out, p_out, a_out


@pytest.mark.parametrize("scene", ["cornell-box", "soup", "big-soup"])
def test03_packets_find_what_single_rays_find(scene):
    """Every lane of a packet gets the single-ray traversal's answer: the
    same distance to the bit, the same primitive (or one it ties with),
    and for shadow rays the same verdict; idle lanes are left alone. Packets
    of rays from one point (coherent) and of scattered rays; the big soup
    has more wide nodes than packet.SMALL_BVH, so its scattered packets take
    the one-ray-at-a-time branch and its coherent ones the packet branch."""
    from renderer.kernels.packet import SMALL_BVH

    rng = np.random.default_rng(11)
    if scene == "cornell-box":
        arrays = load_scene(scene).arrays
    else:
        arrays = random_soup(rng, n_tri=120 if scene == "soup" else 3000)
    assert (arrays.bvh_info.shape[0] > SMALL_BVH) == (scene == "big-soup")
    n = 16 * 120
    span = 0.99 if scene == "cornell-box" else 6.0
    origins = rng.uniform(-span, span, (n, 3))
    origins[: n // 2] = np.repeat(origins[: n // 2: 16], 16, axis=0)  # coherent packets
    dirs = rng.normal(size=(n, 3))
    dirs[: n // 2] = np.abs(dirs[: n // 2]) * np.sign(dirs[: n // 2: 16]).repeat(16, axis=0)
    axis = rng.random(n) < 0.05  # axis-aligned rays: zero direction components
    dirs[axis] = 0.0
    dirs[axis, rng.integers(3, size=axis.sum())] = rng.choice([-1.0, 1.0], axis.sum())
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    active = (rng.random(n) < 0.85).astype(np.int64)
    stack = np.full(STACK_SIZE + 8, -7, np.int64)
    tmax = np.full(n, np.inf)
    t, prim, _ = trace_packets(arrays, origins, dirs, tmax, False, active, stack)
    hits = 0
    for i in range(n):
        if not active[i]:
            assert (t[i], prim[i]) == (np.inf, -1)
            continue
        st, sprim = intersect(arrays, stack, *origins[i], *dirs[i], np.inf)
        assert t[i] == st
        assert prim[i] == sprim or _prim_hit(arrays.tri_isect, arrays.sph, prim[i], *origins[i],
                                             *dirs[i], np.inf) == st
        hits += sprim >= 0
    assert hits > n // 10
    # shadow rays just short of and just past each hit
    for scale, expect in ((0.9999, False), (1.0001, True)):
        tmax = np.where(prim >= 0, t * scale, 1.0)
        live = active * (prim >= 0)
        _, sprim, left = trace_packets(arrays, origins, dirs, tmax, True, live, stack)
        assert np.all(left == 0) if expect else np.all(left == live)
        for i in np.flatnonzero(live):
            assert (sprim[i] >= 0) == occluded(arrays, stack, *origins[i], *dirs[i], tmax[i])
            assert (sprim[i] >= 0) == expect
    assert np.all(stack[STACK_SIZE:] == -7)  # nothing written past the stack
