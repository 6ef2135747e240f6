"""`mlt` (primary-sample-space Metropolis over BDPT): its normalisation, image and variance.

Tolerances come from the estimators' own standard errors (Z = 4.5, fixed
seeds). b's standard error is the bootstrap's (`b_stderr` in its artefact);
an MLT image's comes from its chain units (independent batches), and the
reference's from its camera samples.
"""

import math

import numpy as np
import pytest
from scipy.stats import chi2, t as student_t

from renderer import METHODS, RenderSpec, SpecError, load_scene, merge, run_plan
from renderer.integrators import mlt

from mlt_toy import TOY_CONSTANT, TOY_RAMP, toy_chains

Z = 4.5
Y = np.array([0.212671, 0.715160, 0.072169])  # the luminance MLT targets


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell-box")


@pytest.fixture(scope="module")
def cornell_reference(cornell):
    """cornell-box 16 x 16 at depth 3, 12288 samples per pixel."""
    return reference(cornell, width=16, depth=3, spp=12288)


def reference(scene, *, width, depth, spp, seed=101):
    """The image MLT must match: `bdpt` once registered, else `path-mis`
    (the same image: every method agrees with path-mis at equal depth)."""
    method = "bdpt" if "bdpt" in METHODS else "path-mis"
    # 4 x 4 tiles: BDPT's t = 1 splats need several batches for their variance
    spec = RenderSpec(method=method, spp=spp, depth=depth, width=width, height=width,
                      tile_size=4, seed=seed)
    return merge(width, width, run_plan(scene, spec))


def luminance_mean_and_stderr(film):
    lum = film.mean() @ Y
    var = film.variance_of_mean() @ (Y * Y)  # channels treated as independent: conservative
    return float(lum.mean()), math.sqrt(float(var.sum())) / lum.size


def render_mlt(scene, **kw):
    options = kw.pop("options", {})
    spec = RenderSpec(method="mlt", tile_size=kw.get("width", 16), options=options, **kw)
    films = run_plan(scene, spec)
    return spec, films, merge(spec.width, spec.height, films)


def test01_plan_is_bootstrap_then_chain_units_and_counts_every_mutation(cornell):
    spec = RenderSpec(method="mlt", spp=3, depth=2, width=8, height=6, options={"chains": 5})
    units = METHODS["mlt"].make_plan(spec)
    assert [(u.kind, u.stage, u.needs) for u in units] == \
        [("bootstrap", 0, ())] + [("chains", 1, (0,))] * 5
    assert units[0].pixels == 0
    assert all((u.x0, u.y0, u.x1, u.y1) == (0, 0, 8, 6) for u in units[1:])
    assert [(u.sample_start, u.sample_end) for u in units[1:]] == [(c, c + 1) for c in range(5)]
    assert len(METHODS["mlt"].make_plan(RenderSpec(method="mlt", options={"chains": 100}))) == \
        1 + mlt.CHAIN_UNITS
    films = run_plan(cornell, spec)
    assert films[0].stats["samples"] == 0 and films[0].splat is None
    assert sum(f.stats["samples"] for f in films) == 8 * 6 * 3
    assert sum(f.splat_paths for f in films[1:]) == 8 * 6 * 3
    assert METHODS["mlt"].family == "chains"
    assert METHODS["mlt"].phases == ("bootstrap", "chains")
    for bad in ({"large_step": 1.5}, {"sigma": 0.0}, {"chains": 0}, {"bootstrap": -1},
                {"perturbation": "cauchy"}, {"mutations": 3}):
        with pytest.raises(SpecError):
            RenderSpec(method="mlt", options=bad).validate()


def test02_b_is_the_reference_mean_luminance(cornell, cornell_reference):
    """b = sum over depths of the mean bootstrap luminance is the image's
    mean luminance: within 2 %, and by a z-test. The bootstrap is large
    enough that both standard errors together stay below 2 % / Z, so a 2 %
    error would be caught."""
    spec, films, _ = render_mlt(cornell, spp=1, depth=3, width=16, height=16, seed=5,
                                options={"bootstrap": 400_000})
    b, b_se = films[0].artefact["b"][0], films[0].artefact["b_stderr"][0]
    ref, ref_se = luminance_mean_and_stderr(cornell_reference)
    se = math.hypot(b_se, ref_se)
    assert se < 0.02 * ref / Z, (se, ref)
    assert abs(b - ref) <= 0.02 * ref, (b, ref)
    assert abs(b - ref) <= Z * se, (b, ref, se)


def test03_image_matches_the_reference(cornell, cornell_reference, monkeypatch):
    """The MLT image's mean is within 2 % of the reference's in every
    channel (and by a z-test; the budget keeps the combined standard error
    below 2 % / Z), and its 4x4-pixel blocks agree by a t-test on the chain
    units' batch means (32 units: Student's t with 31 degrees of freedom,
    Sidak over the blocks), with b's own error added."""
    monkeypatch.setattr(mlt, "CHAIN_UNITS", 32)
    spec, films, film = render_mlt(cornell, spp=8192, depth=3, width=16, height=16, seed=6,
                                   options={"bootstrap": 400_000})
    b, b_se = films[0].artefact["b"][0], films[0].artefact["b_stderr"][0]
    ref = cornell_reference
    k = len(films) - 1
    n = np.array([f.splat_paths for f in films[1:]])

    def batch_stats(values):  # (k, ...) per-batch means -> (estimate, its variance)
        w = n.reshape(-1, *[1] * (values.ndim - 1))
        est = (values * w).sum(0) / n.sum()
        return est, ((values - est) ** 2 * w).sum(0) / (k - 1) / n.sum()

    m, m_var = batch_stats(np.array([f.splat.mean(axis=(0, 1)) / f.splat_paths for f in films[1:]]))
    r = ref.mean().mean(axis=(0, 1))
    r_var = ref.variance_of_mean().sum(axis=(0, 1)) / 256 ** 2
    se = np.sqrt(m_var + r_var + (m * b_se / b) ** 2)
    assert np.all(se < 0.02 * r / Z), (se, r)
    assert np.all(np.abs(m - r) <= 0.02 * r), (m, r)
    assert np.all(np.abs(m - r) <= Z * se), (m, r, se)

    def blocks(a):
        return a.reshape(4, 4, 4, 4, 3).mean(axis=(1, 3)) @ Y
    est, var = batch_stats(np.array([blocks(f.splat) / f.splat_paths for f in films[1:]]))
    ref_var = (ref.variance_of_mean() @ (Y * Y)).reshape(4, 4, 4, 4).sum(axis=(1, 3)) / 256.0
    total = var + ref_var + (est * b_se / b) ** 2
    alpha = 1 - (1 - 0.01) ** (1 / est.size)
    limit = student_t.ppf(1 - alpha / 2, k - 1)
    z = (est - blocks(ref.mean())) / np.sqrt(total)
    assert np.all(np.abs(z) <= limit), (z.round(2), limit)


@pytest.mark.parametrize("scene_name, depth, expected", [
    ("furnace-point", 1, 0.5), ("furnace-point", 3, 1 - 0.5 ** 3),
    ("furnace-emitter", 0, 0.5), ("furnace-emitter", 2, 1 - 0.5 ** 3)])
def test04_furnaces(scene_name, depth, expected):
    """Grey furnaces: the mean is analytic (b, by a z-test on b's error),
    and the image is flat (each quadrant's mean by a t-test on the chain
    units' batch means)."""
    scene = load_scene(scene_name)
    spec, films, film = render_mlt(scene, spp=256, depth=depth, width=16, height=16, seed=7,
                                   options={"bootstrap": 100_000})
    b, b_se = films[0].artefact["b"][0], films[0].artefact["b_stderr"][0]
    assert abs(b - expected) <= Z * b_se + 1e-12 * expected, (b, expected, b_se)
    assert abs(film.mean().mean() - b) <= 1e-9 * b  # splats carry b exactly
    quads = np.array([f.splat.reshape(2, 8, 2, 8, 3).sum(axis=(1, 3, 4)) / 3 / 64 / f.splat_paths
                      for f in films[1:]])
    k = len(quads)
    est, spread = quads.mean(0), quads.std(0, ddof=1) / math.sqrt(k)
    limit = student_t.ppf(1 - (1 - (1 - 0.01) ** 0.25) / 2, k - 1)
    assert np.all(np.abs(est - b) <= limit * spread + 1e-12), (est, b, spread)


def test05_deterministic_and_independent_of_tiles(cornell, monkeypatch):
    """Same spec, same bytes (whatever the tile size: the plan ignores it).
    Another grouping of the chains into units resamples their starts (not
    bitwise: documented) but keeps b and the total luminance."""
    kw = dict(spp=4, depth=3, width=16, height=16, seed=9)
    _, a, fa = render_mlt(cornell, **kw)
    _, b, fb = render_mlt(cornell, **kw)
    spec = RenderSpec(method="mlt", tile_size=4, **kw)
    c = run_plan(cornell, spec)
    for x, y, z in zip(a, b, c):
        x.stats.pop("seconds"), y.stats.pop("seconds"), z.stats.pop("seconds")
        assert x.to_bytes() == y.to_bytes() == z.to_bytes()
    monkeypatch.setattr(mlt, "CHAIN_UNITS", 3)
    _, d, fd = render_mlt(cornell, **kw)
    assert len(d) == 4 and d[0].artefact["b"][0] == a[0].artefact["b"][0]
    assert fd.splat_paths == fa.splat_paths
    assert abs((fd.mean() @ Y).mean() - (fa.mean() @ Y).mean()) <= 1e-12


def _toy(n, mutations, large_step, sigma, kind, x0, perturbation=mlt.NORMAL, seed=1):
    out = np.zeros((n, 3))
    toy_chains(seed, n, mutations, large_step, sigma, perturbation, kind,
                   np.ascontiguousarray(x0, dtype=np.float64), np.zeros(3),
                   np.zeros(3, np.int64), np.zeros(3), np.zeros(3, np.int64), out)
    return out


def _uniform_pvalue(values, bins=20):
    counts = np.histogram(values, bins=bins, range=(0.0, 1.0))[0]
    e = len(values) / bins
    return float(chi2.sf(((counts - e) ** 2 / e).sum(), bins - 1))


def test06_small_steps_keep_the_uniform_distribution():
    """On a constant integrand every proposal is accepted: small steps alone
    (wrapped normal, and Kelemen's exponential) must keep uniform states
    uniform on [0, 1) (chi-square per dimension), and move a point by the
    right spread: sigma sqrt(n) for the normal, n E[dv^2] for the exponential."""
    rng = np.random.default_rng(3)
    n = 20_000
    alpha = 1 - (1 - 0.01) ** (1 / 6)
    for perturbation in (mlt.NORMAL, mlt.EXPONENTIAL):
        out = _toy(n, 50, 0.0, 0.01, TOY_CONSTANT, rng.random((n, 3)), perturbation)
        for k in range(3):
            assert _uniform_pvalue(out[:, k]) > alpha, (perturbation, k)
    # from 0.98, the steps cross 1 and must wrap: the wrapped displacement
    # has the spread of the unwrapped one (its own wrap at +-0.5 is 5 sigma away)
    steps, sigma = 100, 0.01
    s1, s2 = 1 / 1024, 1 / 64
    L = math.log(s2 / s1)
    for perturbation, var in ((mlt.NORMAL, steps * sigma ** 2),
                              (mlt.EXPONENTIAL, steps * s2 ** 2 * (1 - math.exp(-2 * L)) / (2 * L))):
        out = _toy(n, steps, 0.0, sigma, TOY_CONSTANT, np.full((n, 3), 0.98), perturbation)
        moved = np.mod(out - 0.98 + 0.5, 1.0) - 0.5
        assert np.all(np.abs(moved.mean(axis=0)) <= Z * math.sqrt(var / n)), perturbation
        assert np.all(np.abs(moved.var(axis=0) - var) <= Z * var * math.sqrt(2 / n)), perturbation


def test07_lazy_catch_up_is_one_step_of_sigma_sqrt_n():
    """A dimension left alone for n iterations takes one normal step of
    sigma sqrt(n) (pbrt-v3's lazy MLTSampler)."""
    n, sigma, missed = 20_000, 0.01, 9
    key = np.uint64(0x1234_5678_9ABC_DEF0)
    moved = np.array([mlt._small_step(0.5, missed, sigma, mlt.NORMAL, key, 2 * i)[0]
                      for i in range(n)]) - 0.5
    var = missed * sigma ** 2
    assert abs(moved.var() - var) <= Z * var * math.sqrt(2 / n)
    assert abs(moved.mean()) <= Z * math.sqrt(var / n)


def test08_chains_sample_the_integrand():
    """Small and large steps with rejections (restoring the backups) leave
    the target f / int f stationary: the final states of independent chains
    started at one point follow it (chi-square on a 10 x 10 grid of the two
    dimensions f reads; the third, unread, stays uniform)."""
    n = 40_000
    out = _toy(n, 200, 0.3, 0.05, TOY_RAMP, np.full((n, 3), 0.3))
    edges = np.linspace(0, 1, 11)
    a, b = edges[:-1], edges[1:]
    g = np.where(a < 0.8, 0.2 * (b - a) + (b * b - a * a) / 2, 0.0)
    h = 0.2 * (b - a) + (b ** 3 - a ** 3) / 3
    expected = n * np.outer(g, h) / (g.sum() * h.sum())
    counts = np.histogram2d(out[:, 0], out[:, 1], bins=[edges, edges])[0]
    assert counts[expected == 0].sum() == 0
    keep = expected > 0
    stat = ((counts[keep] - expected[keep]) ** 2 / expected[keep]).sum()
    assert chi2.sf(stat, keep.sum() - 1) > 0.005, stat
    assert _uniform_pvalue(out[:, 2]) > 0.005


@pytest.mark.parametrize("depth", [0, 1, 3])
def test09_lazy_mutation_readies_every_dimension_mlt_L_reads(cornell, depth):
    """The lazy mutation brings up to date only the dimensions of the
    strategy u[2] selects: mlt_L must not read any other, so redrawing all
    the others never changes its result (checked on random paths)."""
    from renderer.kernels import subpaths as bdpt
    from renderer.kernels.geometry import STACK_SIZE
    from renderer.scene import camera_array

    rng = np.random.default_rng(depth)
    w = h = 16
    cam = camera_array(cornell.camera, w, h)
    dims = bdpt.dims(depth)
    V, stack = bdpt.workspace(depth), np.zeros(STACK_SIZE, np.int64)
    key = np.uint64(12345)
    nonzero = 0
    for i in range(3000):
        x = rng.random(dims)
        last_mod, x_backup, mod_backup = np.zeros(dims, np.int64), np.zeros(dims), np.zeros(dims, np.int64)
        mlt._ready_strategy(x, last_mod, x_backup, mod_backup, depth, 1, 0, True, 0.01, mlt.NORMAL,
                            key, 4 * i * dims)
        ready = last_mod == 1
        a = bdpt.mlt_L(cornell.arrays, cam, w, h, depth, 1, x, V, stack)
        y = x.copy()
        y[~ready] = rng.random((~ready).sum())
        assert bdpt.mlt_L(cornell.arrays, cam, w, h, depth, 1, y, V, stack) == a, (i, depth)
        nonzero += a[0] > 0
    assert nonzero >= 10  # not all black (depth 0: only the light seen directly)


def test15_mlt_counts_the_rays_it_traces():
    """Every unit reports its rays (the dashboard's rays/s): the bootstrap and
    each chain unit trace at least one ray per path or mutation."""
    from renderer import load_scene, run_plan
    from renderer import RenderSpec as Spec

    spec = Spec(method="mlt", spp=2, depth=3, width=8, height=8, seed=3,
                options={"chains": 16, "bootstrap": 256})
    films = run_plan(load_scene("cornell-box"), spec)
    for film in films:
        assert film.stats["rays"] >= film.stats["paths"] > 0, film.stats


def test16_var_channels_carry_the_bootstrap_normalization_error(cornell):
    """Every chain unit is scaled by the one bootstrap estimate b, so b's error
    is an error of every pixel that the chain units' batch spread cannot see.
    The var channels add I^2 (b_stderr / b)^2 to each pixel (film.py,
    `splat_scale_rel_var`); and b_stderr is honest: with expected-value
    splatting every mutation carries luminance b W H exactly, so the image's
    mean luminance is b times a constant and its spread over seeds is b's. Over
    8 seeds its variance over the claimed one lies within the chi-square
    (7 dof) bounds at one in a thousand each side."""
    weights = np.array([0.212671, 0.715160, 0.072169])  # mlt.luminance
    means, claimed = [], []
    for k in range(8):
        spec = RenderSpec(method="mlt", spp=16, depth=5, width=48, height=48, tile_size=48,
                          seed=400 + k)
        film = merge(48, 48, run_plan(cornell, spec))
        rel_var = film.splat_scale_rel_var
        assert rel_var > 0
        with_b = film.variance_of_mean()
        film.splat_scale_rel_var = 0.0
        batches_only = film.variance_of_mean()
        assert np.allclose(with_b - batches_only, film.mean() ** 2 * rel_var, rtol=1e-12, atol=0)
        means.append(float((film.mean() @ weights).mean()))
        claimed.append(rel_var)
    means = np.array(means)
    ratio = means.var(ddof=1) / (means.mean() ** 2 * np.mean(claimed))
    assert chi2.ppf(0.001, 7) / 7 <= ratio <= chi2.ppf(0.999, 7) / 7, ratio
