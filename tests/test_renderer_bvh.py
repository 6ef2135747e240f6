"""The BVH against the obvious answer: every primitive tested in turn."""

import numpy as np
import pytest

from renderer import build_scene, load_scene, resolve_document
from renderer.kernels.geometry import _prim_hit, intersect, occluded


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
    stack = np.empty(64, np.int64)
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
