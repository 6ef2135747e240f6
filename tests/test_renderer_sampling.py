"""Sampling routines against their pdfs (chi-square, see chi2util.py).

Each test draws 10^6 directions from a kernel and checks them against the
pdf the integrators divide by. Family-wise alpha = 0.01, Sidak-corrected
over the tests of this module. A deliberately wrong pdf must be rejected,
so the test can fail.
"""

import math

import numpy as np
from numba import njit

from chi2util import chi2_pvalue, expected_counts, histogram, sidak
from renderer import build_scene, resolve_document
from renderer.kernels.bsdf import diffuse_sample
from renderer.kernels.lights import sample_light
from renderer.kernels.rng import sample_key, uniform
from renderer.kernels.sampling import uniform_hemisphere

N = 1_000_000
ALPHA = sidak(0.01, 4)


@njit
def _draw_cosine(n, nx, ny, nz):
    out = np.empty((n, 3))
    for i in range(n):
        key = sample_key(7, i, 0)
        wx, wy, wz, _, _ = diffuse_sample(nx, ny, nz, uniform(key, 0), uniform(key, 1))
        out[i, 0], out[i, 1], out[i, 2] = wx, wy, wz
    return out


@njit
def _draw_uniform(n):
    out = np.empty((n, 3))
    for i in range(n):
        key = sample_key(8, i, 0)
        out[i, 0], out[i, 1], out[i, 2] = uniform_hemisphere(uniform(key, 0), uniform(key, 1))
    return out


@njit
def _draw_light(sc, n, px, py, pz):
    out = np.empty((n, 3))
    pdfs = np.empty(n)
    for i in range(n):
        key = sample_key(9, i, 0)
        r = sample_light(sc, px, py, pz, uniform(key, 0), uniform(key, 1))
        out[i, 0], out[i, 1], out[i, 2] = r[0], r[1], r[2]
        pdfs[i] = r[4]
    return out, pdfs


def cosine_pdf(d):
    return np.maximum(d[:, 2], 0.0) / np.pi


def test01_cosine_hemisphere_sampling_matches_cos_over_pi():
    counts = histogram(_draw_cosine(N, 0.0, 0.0, 1.0))
    assert chi2_pvalue(counts, expected_counts(cosine_pdf, N)) > ALPHA
    # the same samples are not uniform on the hemisphere: the test has teeth
    uniform_pdf = lambda d: np.where(d[:, 2] > 0, 1 / (2 * np.pi), 0.0)  # noqa: E731
    assert chi2_pvalue(counts, expected_counts(uniform_pdf, N)) < ALPHA


def test02_uniform_hemisphere_sampling_matches_one_over_two_pi():
    counts = histogram(_draw_uniform(N))
    uniform_pdf = lambda d: np.where(d[:, 2] > 0, 1 / (2 * np.pi), 0.0)  # noqa: E731
    assert chi2_pvalue(counts, expected_counts(uniform_pdf, N)) > ALPHA
    assert chi2_pvalue(counts, expected_counts(cosine_pdf, N)) < ALPHA


def _light_scene(shape):
    return build_scene(resolve_document({
        "camera": {"origin": [0, 0, -5], "target": [0, 0, 0], "fov": 30},
        "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
        "shapes": [dict(shape, material="m", emitter={"type": "area", "radiance": 1})]})).arrays


def test03_sphere_light_cone_sampling_matches_its_pdf():
    """From the origin, a sphere of radius 1 centred at (0, 0, 2) subtends a
    cone of half-angle 30 degrees around +z: the pdf is uniform inside."""
    sc = _light_scene({"type": "sphere", "center": [0, 0, 2], "radius": 1})
    dirs, pdfs = _draw_light(sc, N, 0.0, 0.0, 0.0)
    cos_max = math.sqrt(1 - 0.25)
    pdf_value = 1 / (2 * np.pi * (1 - cos_max))
    assert np.allclose(pdfs, pdf_value)
    cone_pdf = lambda d: np.where(d[:, 2] >= cos_max, pdf_value, 0.0)  # noqa: E731
    assert chi2_pvalue(histogram(dirs), expected_counts(cone_pdf, N, sub=16)) > ALPHA
    wide = lambda d: np.where(d[:, 2] >= 0.8, 1 / (2 * np.pi * 0.2), 0.0)  # noqa: E731
    assert chi2_pvalue(histogram(dirs), expected_counts(wide, N, sub=16)) < ALPHA


def test04_rectangle_light_sampling_matches_its_solid_angle_pdf():
    """A 2 x 2 square light in the plane z = 1 facing the origin: the
    solid-angle pdf of direction d is dist^2 / (cos_light * area)."""
    sc = _light_scene({"type": "rectangle", "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": 180}},
                                                         {"translate": [0, 0, 1]}]})
    dirs, pdfs = _draw_light(sc, N, 0.0, 0.0, 0.0)

    def rect_pdf(d):
        z = np.maximum(d[:, 2], 1e-12)
        x, y = d[:, 0] / z, d[:, 1] / z  # where the ray meets z = 1
        inside = (d[:, 2] > 0) & (np.abs(x) <= 1) & (np.abs(y) <= 1)
        dist2 = x * x + y * y + 1
        return np.where(inside, dist2 / (d[:, 2] * 4.0), 0.0)

    assert np.allclose(pdfs, rect_pdf(dirs), rtol=1e-9)
    assert chi2_pvalue(histogram(dirs), expected_counts(rect_pdf, N, sub=16)) > ALPHA


def test05_the_quarter_turn_sincos_is_libm_to_an_ulp():
    # The concentric map's cos and sin (sampling.sincos_quarter) are
    # polynomials, not libm's calls: within an ulp of libm on [-pi/4, pi/4],
    # and the map's points are libm's map's points to rounding (its second
    # branch swaps cos and sin: a swap the wrong way round would keep the
    # radius and the pdf, so the points are compared). (Not a chi-square test: the
    # polynomials are exact enough that no histogram could tell them apart,
    # so their error is checked directly; test01 checks the map's pdf.)
    from renderer.kernels.sampling import concentric_disk, sincos_quarter

    th = np.concatenate([np.linspace(-math.pi / 4, math.pi / 4, 100_001),
                         [0.0, 1e-300, -1e-8, math.pi / 4, -math.pi / 4]])
    for t in th:
        c, s = sincos_quarter(t)
        assert abs(c - math.cos(t)) <= 2 * math.ulp(math.cos(t))
        assert abs(s - math.sin(t)) <= 2 * math.ulp(abs(math.sin(t)) or 5e-324)
    rng = np.random.default_rng(5)
    for u1, u2 in rng.random((20_000, 2)):
        x, y = concentric_disk(u1, u2)
        a, b = 2 * u1 - 1, 2 * u2 - 1
        r, phi = (a, math.pi / 4 * (b / a)) if abs(a) > abs(b) else \
            (b, math.pi / 2 - math.pi / 4 * (a / b))  # Shirley-Chiu with libm
        assert abs(math.hypot(x, y) - abs(r)) <= 4e-16
        assert abs(x - r * math.cos(phi)) <= 1e-15 and abs(y - r * math.sin(phi)) <= 1e-15


def test06_a_stratified_pair_stays_stratified_on_the_lights():
    """sample_light picks the light and the light's triangle with the point's
    first number and reuses it for the point (kernels/lights.py): a grid of
    pairs lands as evenly on two square lights (four triangles) as on one
    triangle. Picked from a third number instead, each pixel's points split
    among lights and triangles at random, and the cells' counts scatter as
    much as independent points' do (chi-square statistic about its 127
    degrees of freedom; here it stays under a tenth of them)."""
    sc = build_scene(resolve_document({
        "camera": {"origin": [0, 0, -5], "target": [0, 0, 0], "fov": 30},
        "materials": {"m": {"type": "diffuse", "albedo": 0.5}},
        "shapes": [{"type": "rectangle", "material": "m", "emitter": {"type": "area", "radiance": 1},
                    "to_world": [{"rotate": {"axis": [1, 0, 0], "angle": 180}},
                                 {"translate": [x, 0, 1]}]} for x in (-1.5, 1.5)]})).arrays
    g = 64
    u = (np.arange(g) + 0.5) / g
    counts = np.zeros((2, 8, 8))
    for u1 in u:
        for u2 in u:
            wx, wy, wz, dist, pdf = sample_light(sc, 0.0, 0.0, 0.0, u1, u2)[:5]
            qx, qy = wx * dist, wy * dist  # the point on the light, at z = 1
            light = int(qx > 0)
            cx = min(int((qx - (1.5 if light else -1.5) + 1) * 4), 7)
            cy = min(int((qy + 1) * 4), 7)
            counts[light, cx, cy] += 1
    expected = g * g / counts.size
    assert counts[0].sum() == counts[1].sum() == g * g / 2
    assert ((counts - expected) ** 2 / expected).sum() < 12.7


def test07_the_full_turn_sincos_is_libm_to_rounding():
    # sampling.sincos_turn(u) = (cos 2 pi u, sin 2 pi u) by the nearest
    # quarter turn and the quarter-turn polynomials (test05), in place of
    # libm's calls in the uniform sphere and hemisphere, the sphere light's
    # cone and GGX's visible normals. Against libm's cos(2 pi u): the
    # difference is libm's own rounding of the angle 2 pi u (up to an ulp of
    # 2 pi, 8.9e-16) plus an ulp or two; a quarter turn taken the wrong way
    # (a sign, a swap) would be off by O(1). The points stay on the unit
    # circle to rounding. Every octant boundary and both ends are included.
    from renderer.kernels.sampling import sincos_turn

    rng = np.random.default_rng(13)
    us = np.concatenate([np.linspace(0.0, 1.0, 80_001)[:-1], rng.random(40_000),
                         np.arange(8) / 8.0, [1.0 - 2.0 ** -53, 1e-300, 0.25 - 2.0 ** -55]])
    for u in us:
        c, s = sincos_turn(u)
        assert abs(c - math.cos(2.0 * math.pi * u)) <= 1.2e-15
        assert abs(s - math.sin(2.0 * math.pi * u)) <= 1.2e-15
        assert abs(c * c + s * s - 1.0) <= 4.5e-16
