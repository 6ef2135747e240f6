"""The glossy material (GGX or Beckmann rough conductor, renderer/kernels/ggx.py)
and its scene-format entry. A negative roughness argument is the Beckmann
lobe of that alpha (the kernels' signed roughness).

Sampling is checked as in test_renderer_sampling.py: 10^6 directions from
`glossy_sample` binned and compared (chi-square) with `glossy_eval`'s pdf,
family-wise alpha 0.01, Sidak-corrected; deliberately wrong pdfs must be
rejected. Then the pointwise agreement of sample and eval, reciprocity,
energy (white furnace of the single-scattering model) and the pdf's mass.
"""

import json
import math

import numpy as np
import pytest
from numba import njit

from chi2util import COS_BINS, PHI_BINS, chi2_pvalue, expected_counts, histogram, sidak
from renderer import SceneError, build_scene, load_scene, resolve_document
from renderer.kernels.bsdf import MAT_GLOSSY, diffuse_sample
from renderer.kernels.ggx import glossy_eval, glossy_sample
from renderer.kernels.rng import sample_key, uniform
from renderer.scene import MAT_GLOSSY as SCENE_MAT_GLOSSY

N = 1_000_000
THETAS = (0.0, 30.0, 60.0, 80.0)
ALPHAS = (0.1, 0.3, 0.7)
DIFFUSE_NORMALS = ((0.0, 0.6, 0.8), (0.48, -0.6, 0.64))
SIGNS = (1.0, -1.0)  # GGX, Beckmann
ALPHA = sidak(0.01, len(THETAS) * len(ALPHAS) * len(SIGNS) + len(DIFFUSE_NORMALS))


def _wo(theta_deg):
    t = math.radians(theta_deg)
    return math.sin(t), 0.0, math.cos(t)


@njit
def _draw_glossy(n, seed, nx, ny, nz, wox, woy, woz, alpha, spec):
    """Sampled directions (rows of NaN where the sample failed), weights, pdfs."""
    dirs = np.empty((n, 3))
    weights = np.empty(n)
    pdfs = np.empty(n)
    for i in range(n):
        key = sample_key(seed, i, 0)
        r = glossy_sample(nx, ny, nz, wox, woy, woz, alpha, spec, spec, spec,
                          uniform(key, 0), uniform(key, 1))
        if r[6] > 0.0:
            dirs[i, 0], dirs[i, 1], dirs[i, 2] = r[0], r[1], r[2]
        else:
            dirs[i, 0] = dirs[i, 1] = dirs[i, 2] = np.nan
        weights[i] = r[3]
        pdfs[i] = r[6]
    return dirs, weights, pdfs


@njit
def _eval_many(dirs, nx, ny, nz, wox, woy, woz, alpha, spec):
    """glossy_eval for wi = each row of dirs: (n, 4) of f_rgb and pdf."""
    out = np.empty((dirs.shape[0], 4))
    for i in range(dirs.shape[0]):
        r = glossy_eval(nx, ny, nz, wox, woy, woz, dirs[i, 0], dirs[i, 1], dirs[i, 2],
                        alpha, spec, spec, spec)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = r[0], r[1], r[2], r[3]
    return out


@njit
def _draw_diffuse(n, nx, ny, nz):
    out = np.empty((n, 3))
    for i in range(n):
        key = sample_key(11, i, 0)
        wx, wy, wz, _, _ = diffuse_sample(nx, ny, nz, uniform(key, 0), uniform(key, 1))
        out[i, 0], out[i, 1], out[i, 2] = wx, wy, wz
    return out


def glossy_pdf(wo, alpha):
    return lambda d: _eval_many(np.ascontiguousarray(d), 0.0, 0.0, 1.0, *wo, alpha, 1.0)[:, 3]


def upper_counts(fn, n, sub=16):
    """expected_counts for a function that vanishes for cos theta < 0: the
    cell straddling the horizon (COS_BINS is odd) is integrated over its upper
    part only, so the discontinuity at the horizon costs no accuracy."""
    counts = expected_counts(fn, n, sub)
    mid = COS_BINS // 2
    x, w = np.polynomial.legendre.leggauss(sub)
    c_hi = -1 + 2 * (mid + 1) / COS_BINS
    cos_t = c_hi / 2 + c_hi / 2 * x
    p_edges = np.linspace(0, 2 * np.pi, PHI_BINS + 1)
    p_half = (p_edges[1] - p_edges[0]) / 2
    phi = (p_edges[:-1, None] + p_half) + p_half * x[None, :]  # (P, sub)
    st = np.sqrt(1 - cos_t * cos_t)
    ct, ph = np.broadcast_arrays(cos_t[None, :, None], phi[:, None, :])
    sst = np.broadcast_to(st[None, :, None], ct.shape)
    dirs = np.stack([sst * np.cos(ph), sst * np.sin(ph), ct], axis=-1).reshape(-1, 3)
    values = fn(dirs).reshape(PHI_BINS, sub, sub)
    counts[mid] = n * (values * (w[:, None] * w[None, :])).sum(axis=(1, 2)) * (c_hi / 2) * p_half
    return counts


def _valid(dirs):
    return dirs[~np.isnan(dirs[:, 0])]


# ---------------------------------------------------------------------------

@pytest.mark.parametrize("sign", SIGNS)
def test01_eval_is_reciprocal_and_one_sided(sign):
    rng = np.random.default_rng(1)
    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    for _ in range(200):
        a, b = rng.normal(size=(2, 3))
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        a, b = a * np.sign(a @ n), b * np.sign(b @ n)
        alpha = sign * rng.uniform(0.02, 1.0)
        ab = glossy_eval(*n, *a, *b, alpha, 0.9, 0.5, 0.1)
        ba = glossy_eval(*n, *b, *a, alpha, 0.9, 0.5, 0.1)
        assert ab[:3] == pytest.approx(ba[:3], rel=1e-12)
        # Beckmann's exp(-tan^2 / alpha^2) underflows to 0 far off its peak
        assert min(ab) > 0 if sign > 0 else min(ab) >= 0 and (ab[3] > 0) == (ab[0] > 0)
        assert glossy_eval(*n, *-a, *b, alpha, 0.9, 0.5, 0.1) == (0.0, 0.0, 0.0, 0.0)
        assert glossy_eval(*n, *a, *-b, alpha, 0.9, 0.5, 0.1) == (0.0, 0.0, 0.0, 0.0)
        assert glossy_sample(*n, *-a, alpha, 0.9, 0.5, 0.1, 0.3, 0.7)[6] == 0.0


@pytest.mark.parametrize("sign", SIGNS)
def test02_sample_returns_evals_pdf_and_f_cos_over_pdf(sign):
    n = np.array([0.48, -0.6, 0.64])
    wo = np.array([0.0, 0.6, 0.8])  # 41 degrees from n
    for alpha in (sign * 0.05, sign * 0.4, sign * 1.0):
        dirs, weights, pdfs = _draw_glossy(20_000, 3, *n, *wo, alpha, 0.3)
        ok = pdfs > 0
        assert 0.5 < ok.mean() <= 1.0
        assert np.all(weights[~ok] == 0)
        ev = _eval_many(dirs[ok], *n, *wo, alpha, 0.3)
        assert np.allclose(ev[:, 3], pdfs[ok], rtol=1e-9)
        cos_i = dirs[ok] @ n
        assert np.allclose(ev[:, 0] * cos_i / ev[:, 3], weights[ok], rtol=1e-9)
        assert np.allclose(np.linalg.norm(dirs[ok], axis=1), 1.0)


@pytest.mark.parametrize("sign", SIGNS)
@pytest.mark.parametrize("alpha", ALPHAS)
@pytest.mark.parametrize("theta", THETAS)
def test03_chi2_sampling_matches_eval_pdf(theta, alpha, sign):
    """GGX's visible normals and Beckmann's D(h) cos_h sampling."""
    alpha *= sign
    wo = _wo(theta)
    dirs, _, _ = _draw_glossy(N, 5, 0.0, 0.0, 1.0, *wo, alpha, 1.0)
    counts = histogram(_valid(dirs))
    assert chi2_pvalue(counts, upper_counts(glossy_pdf(wo, alpha), N)) > ALPHA


def test04_chi2_rejects_wrong_pdfs():
    wo = _wo(60.0)
    dirs, _, _ = _draw_glossy(N, 6, 0.0, 0.0, 1.0, *wo, 0.3, 1.0)
    counts = histogram(_valid(dirs))
    assert chi2_pvalue(counts, upper_counts(glossy_pdf(wo, 0.3), N)) > ALPHA
    # an alpha 10 % off
    assert chi2_pvalue(counts, upper_counts(glossy_pdf(wo, 0.33), N)) < ALPHA

    # the pdf of sampling D(h) cos_h (all normals, not just visible ones)
    def ndf_pdf(d):
        h = d + np.asarray(wo)
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        a2 = 0.3 ** 2
        dh = a2 / (np.pi * (h[:, 2] ** 2 * (a2 - 1) + 1) ** 2)
        return np.where(d[:, 2] > 0, dh * h[:, 2] / (4 * np.abs(h @ np.asarray(wo))), 0.0)

    assert chi2_pvalue(counts, upper_counts(ndf_pdf, N)) < ALPHA
    # Beckmann's samples are not GGX's distribution of the same alpha
    dirs, _, _ = _draw_glossy(N, 6, 0.0, 0.0, 1.0, *wo, -0.3, 1.0)
    counts = histogram(_valid(dirs))
    assert chi2_pvalue(counts, upper_counts(glossy_pdf(wo, -0.3), N)) > ALPHA
    assert chi2_pvalue(counts, upper_counts(glossy_pdf(wo, 0.3), N)) < ALPHA


@pytest.mark.parametrize("normal", DIFFUSE_NORMALS)
def test05_chi2_diffuse_sampling_around_tilted_normals(normal):
    n = np.asarray(normal)
    counts = histogram(_draw_diffuse(N, *n))
    cos_pdf = lambda d: np.maximum(d @ n, 0.0) / np.pi  # noqa: E731
    assert chi2_pvalue(counts, expected_counts(cos_pdf, N, sub=16)) > ALPHA
    flat = lambda d: np.maximum(d[:, 2], 0.0) / np.pi  # noqa: E731  (the untilted lobe)
    assert chi2_pvalue(counts, expected_counts(flat, N, sub=16)) < ALPHA


@pytest.mark.parametrize("sign", SIGNS)
@pytest.mark.parametrize("theta", THETAS)
def test06_energy_conservation_and_weights_match_the_integral_of_f_cos(theta, sign):
    """Specular 1 (F = 1): the albedo is 1 minus the multiple-scattering
    loss. The sampled mean of the weights must agree with the quadrature of
    f cos over the hemisphere, and never exceed 1."""
    wo = _wo(theta)
    for alpha in np.multiply(ALPHAS, sign):
        _, weights, _ = _draw_glossy(100_000, 7, 0.0, 0.0, 1.0, *wo, alpha, 1.0)
        albedo = weights.mean()
        assert albedo <= 1.01

        def f_cos(d):
            f = _eval_many(np.ascontiguousarray(d), 0.0, 0.0, 1.0, *wo, alpha, 1.0)[:, 0]
            return f * np.maximum(d[:, 2], 0.0)

        integral = upper_counts(f_cos, 1).sum()
        assert albedo == pytest.approx(integral, rel=0.01, abs=3 * weights.std() / math.sqrt(len(weights)))
        if theta == 0.0 and abs(alpha) == 0.1:
            assert albedo >= 0.9
    # Schlick with F0 < 1 reflects more at grazing angles, but never more than 1
    _, weights, _ = _draw_glossy(100_000, 8, 0.0, 0.0, 1.0, *wo, sign * 0.1, 0.3)
    assert 0.3 * 0.8 <= weights.mean() <= 1.0


@pytest.mark.parametrize("sign", SIGNS)
@pytest.mark.parametrize("theta", THETAS)
def test07_pdf_mass_is_the_share_of_samples_above_the_horizon(theta, sign):
    wo = _wo(theta)
    for alpha in np.multiply(ALPHAS, sign):
        mass = upper_counts(glossy_pdf(wo, alpha), 1).sum()
        assert mass <= 1.001
        _, _, pdfs = _draw_glossy(100_000, 9, 0.0, 0.0, 1.0, *wo, alpha, 1.0)
        assert mass == pytest.approx((pdfs > 0).mean(), abs=0.005)


# ---------------------------------------------------------------------------
# Scene format

MINIMAL = {
    "camera": {"origin": [0, 0, 5], "target": [0, 0, 0], "fov": 40},
    "materials": {"g": {"type": "glossy", "specular": [0.9, 0.6, 0.3], "roughness": 0.2}},
    "shapes": [{"type": "rectangle", "material": "g"}],
}


def test08_glossy_material_resolves_and_builds():
    doc = resolve_document(MINIMAL)
    assert doc["materials"]["g"] == {"type": "glossy", "specular": [0.9, 0.6, 0.3], "roughness": 0.2}
    a = build_scene(doc).arrays
    assert MAT_GLOSSY == SCENE_MAT_GLOSSY == 3
    assert a.mat_type[0] == MAT_GLOSSY
    assert a.mat_rgb[0].tolist() == [0.9, 0.6, 0.3] and a.mat_param[0, 1] == 0.2
    defaults = json.loads(json.dumps(MINIMAL))
    defaults["materials"]["g"] = {"type": "glossy"}
    assert resolve_document(defaults)["materials"]["g"] == {
        "type": "glossy", "specular": [1.0, 1.0, 1.0], "roughness": 0.1}
    # Beckmann is the kernels' negative roughness; GGX, the default, is left out
    defaults["materials"]["g"] = {"type": "glossy", "roughness": 0.2, "distribution": "beckmann"}
    doc = resolve_document(defaults)
    assert doc["materials"]["g"]["distribution"] == "beckmann"
    assert build_scene(doc).arrays.mat_param[0, 1] == -0.2
    defaults["materials"]["g"]["distribution"] = "ggx"
    assert "distribution" not in resolve_document(defaults)["materials"]["g"]


@pytest.mark.parametrize("fields, location, words", [
    ({"roughness": 0}, "materials.g.roughness", ">= 0.001"),
    ({"roughness": 1.5}, "materials.g.roughness", "<= 1"),
    ({"roughness": "rough"}, "materials.g.roughness", "finite number"),
    ({"specular": [1.2, 0, 0]}, "materials.g.specular", "<= 1"),
    ({"specular": [0.5, -0.1, 0]}, "materials.g.specular[1]", ">= 0"),
    ({"specular": [0.5, 0.5]}, "materials.g.specular", "3 numbers"),
    ({"distribution": "phong"}, "materials.g.distribution", "ggx, beckmann"),
])
def test09_invalid_glossy_material_names_the_field(fields, location, words):
    doc = json.loads(json.dumps(MINIMAL))
    doc["materials"]["g"].update(fields)
    with pytest.raises(SceneError) as err:
        resolve_document(doc)
    assert err.value.location == location
    assert words in err.value.message


def test10_veach_mis_scene():
    """shared/scenes/veach-mis.md, with a fourth light of the same power."""
    a = load_scene("veach-mis").arrays
    glossy = a.mat_type == MAT_GLOSSY
    assert sorted(a.mat_param[glossy, 1]) == [0.01, 0.05, 0.1, 0.25]
    assert len(a.tri_p) == 4 * 12 + 2 * 2
    assert len(a.light_type) == 4 and np.all(a.light_sphere == np.arange(4))
    power = a.light_rgb[:, 0] * a.sph[:, 3] ** 2
    assert np.allclose(power, 7.59909, rtol=1e-5)
    assert np.all(a.mat_rgb[a.sph_mat] == 0)  # black sphere surfaces
    assert a.sph[:, 2].tolist() == [-2.8, 0.0, 1.35, 2.7]


def test11_beckmann_is_normalised_and_its_masking_fit_matches_the_exact_smith_form():
    """D(h) cos_h integrates to 1 over the hemisphere, and Walter et al.'s
    rational Lambda (the one Mitsuba's G1 uses) is within 0.4 % of the
    exact Smith G1 = 2 / (1 + erf(a) + exp(-a^2) / (a sqrt(pi)))."""
    from renderer.kernels.ggx import beckmann_D, beckmann_lambda

    theta = np.linspace(0.0, np.pi / 2, 200_001)
    for alpha in (0.05, 0.25, 1.0):
        d = np.array([beckmann_D(c, alpha) for c in np.cos(theta)])
        mass = np.trapezoid(2 * np.pi * d * np.cos(theta) * np.sin(theta), theta)
        assert mass == pytest.approx(1.0, rel=1e-5)
        for cos_t in np.linspace(0.02, 0.999, 60):
            a = cos_t / (alpha * math.sqrt(1 - cos_t * cos_t))
            exact = 2 / (1 + math.erf(a) + math.exp(-a * a) / (a * math.sqrt(math.pi)))
            assert 1 / (1 + beckmann_lambda(cos_t, alpha)) == pytest.approx(exact, rel=4e-3)


def test12_a_textured_roughness_keeps_its_materials_distribution():
    """The texture gives alpha's size, the material its sign (Beckmann < 0)."""
    from renderer.kernels.shading import shade_hit

    for distribution, sign in (("beckmann", -1.0), ("ggx", 1.0)):
        doc = resolve_document({**MINIMAL, "textures": {"c": {"type": "checkerboard"}},
                                "materials": {"g": {"type": "glossy", "roughness": {"texture": "c"},
                                                    "distribution": distribution}}})
        sc = build_scene(doc).arrays
        # the checkerboard's color0 (0.4, Mitsuba's default) at uv (0.55, 0.55)
        alpha = shade_hit(sc, 0, 0.1, 0.1, 0.0, 0.0, 0.0, -1.0)[12]
        assert alpha == pytest.approx(sign * 0.4)
