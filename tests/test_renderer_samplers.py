"""Pixel samplers (renderer/samplers/): the properties each construction promises.

Numbered by concern (Mitsuba's habit): 01 registry and API, 02 purity
(same values whatever the order or tile), 03 per-sampler stratification
properties, 04 quality comparisons between samplers (discrepancy, spectrum,
integration error), 05 kernels against the plain-Python references in
renderer/samplers/naive.py. Fixed seeds throughout, so every comparison is
deterministic; each test fails when its property breaks.
"""

import math

import numpy as np
import pytest
from numba import njit

from renderer.kernels.rng import sample_key, uniform
from renderer.registry import SAMPLERS
from renderer.samplers import (SAMPLER_RANDOM, SAMPLER_SOBOL, bluenoise, fill_2d, halton,
                               memo_rows, naive, points, sample_1d, sample_2d, sobol, u2d)
from renderer.samplers.common import permute
from renderer.samplers.dispatch import MEMO_MAX_BYTES

SEED = 20261122
NAMES = ["random", "uniform", "jittered", "nrooks", "multijitter", "hammersley", "halton",
         "sobol", "bluenoise"]


def _grid_counts(p, nx, ny):
    ix = np.floor(p[:, 0] * nx).astype(int)
    iy = np.floor(p[:, 1] * ny).astype(int)
    return np.bincount(iy * nx + ix, minlength=nx * ny)


def _star_discrepancy(p):
    """Exact 2D star discrepancy (the same estimator for every sampler), O(n^2) memory."""
    n = len(p)
    xs = np.unique(np.append(p[:, 0], 1.0))
    ys = np.unique(np.append(p[:, 1], 1.0))
    closed = (p[:, 0][:, None] <= xs).T.astype(float) @ (p[:, 1][:, None] <= ys).astype(float)
    opened = (p[:, 0][:, None] < xs).T.astype(float) @ (p[:, 1][:, None] < ys).astype(float)
    volume = xs[:, None] * ys[None, :]
    return max((closed / n - volume).max(), (volume - opened / n).max())


# -- 01 registry and API ------------------------------------------------------------------

def test01_registry_names_and_ids():
    assert list(SAMPLERS) == NAMES
    assert [SAMPLERS[n].id for n in NAMES] == list(range(len(NAMES)))
    assert SAMPLERS["random"].id == SAMPLER_RANDOM == 0


@njit
def _former_random(seed, pixel, index, dim):  # the integrators' original draw, in a kernel
    return uniform(sample_key(seed, pixel, index), dim)


def test01_random_is_the_former_hash():
    # Renders made before the sampler library keep their bytes.
    for pixel, index, dim in [(0, 0, 0), (5, 3, 1), (77, 15, 6), (1234, 2, 9)]:
        assert sample_1d(SAMPLER_RANDOM, SEED, pixel, index, 16, dim) == \
            _former_random(SEED, pixel, index, dim)


@pytest.mark.parametrize("name", NAMES)
def test01_values_in_unit_interval(name):
    sid = SAMPLERS[name].id
    for spp in (1, 2, 3, 5, 12, 16, 17, 64, 100):
        for dim in (0, 2, 5):
            # two blocks: indices past spp too
            p = points(name, SEED, 3, spp, dim, count=2 * spp)
            assert np.all(p >= 0.0) and np.all(p < 1.0), (spp, dim)
    assert 0.0 <= sample_1d(sid, SEED, 1, 0, 1, 0) < 1.0


@pytest.mark.parametrize("name", NAMES)
def test01_1d_and_2d_reads_agree(name):
    sid = SAMPLERS[name].id
    for index in range(6):
        for dim in range(8):
            u, v = sample_2d(sid, SEED, 9, index, 6, dim)
            assert u == sample_1d(sid, SEED, 9, index, 6, dim)
            assert v == sample_1d(sid, SEED, 9, index, 6, dim + 1)


# -- 02 purity: order, tile and replay invariance -----------------------------------------

@pytest.mark.parametrize("name", NAMES)
def test02_consistent_values_in_any_order(name):
    """pbrt's ConsistentValues: the same (pixel, index, dim) gives the same value whatever
    was drawn before it, and a second "tile" walking the pixels differently agrees."""
    sid, spp, dims = SAMPLERS[name].id, 16, 8
    pixels = [0, 1, 37, 4096]
    forward = {}
    for pixel in pixels:  # tile A: pixel-major, sample-major, dims in order
        for index in range(spp):
            for dim in range(dims):
                forward[pixel, index, dim] = sample_1d(sid, SEED, pixel, index, spp, dim)
    rng = np.random.default_rng(1)
    order = list(forward)
    rng.shuffle(order)  # tile B: everything interleaved at random
    for key in order:
        pixel, index, dim = key
        assert sample_1d(sid, SEED, pixel, index, spp, dim) == forward[key]
    for pixel in pixels:  # the batch kernel agrees with the scalar one
        for dim in (0, 2, 6):
            batch = points(name, SEED, pixel, spp, dim)
            assert [tuple(b) for b in batch] == \
                [(forward[pixel, i, dim], forward[pixel, i, dim + 1]) for i in range(spp)]
    # a replay of a single sample in a fresh buffer
    one = np.empty((1, 2))
    fill_2d(sid, SEED, 37, 11, spp, 2, one)
    assert tuple(one[0]) == (forward[37, 11, 2], forward[37, 11, 3])


@njit
def _sobol_memo_draws(seed, spp, visits, memo, out):
    """u2d's sobol path with a memo, over (pixel, index, dim) visits in the given order."""
    for k in range(visits.shape[0]):
        out[k, 0], out[k, 1] = u2d(SAMPLER_SOBOL, np.uint64(0), seed, visits[k, 0], visits[k, 1],
                                   spp, visits[k, 2], memo)


@njit
def _sobol_plain_draws(seed, spp, visits, out):
    """The plain kernel (sample_2d, no memo) over the same visits."""
    for k in range(visits.shape[0]):
        out[k, 0], out[k, 1] = sample_2d(SAMPLER_SOBOL, seed, visits[k, 0], visits[k, 1], spp,
                                         visits[k, 2])


# The windows of samples a tile kernel may draw (memo_rows): none (the
# entries layout), every sample, and parts of the block (progressive passes):
# its head, its tail, a middle part whose span wraps around the block.
_WINDOWS = {"entries": None, "whole": (0, 1), "head": (0, 0.25), "tail": (0.75, 1),
            "middle": (0.37, 0.83)}


@pytest.mark.parametrize("window", list(_WINDOWS))
@pytest.mark.parametrize("spp", [1, 16, 10, 64, 100])
def test02_sobol_memo_gives_the_same_values(spp, window):
    # The tile kernels keep one pixel's sample order (and, in the tables
    # layout, its pairs' points over the samples of the unit) in a per-row
    # memo (samplers/dispatch.py memo_rows); the values must be those of the
    # plain kernel whatever the order of the visits inside the window:
    # pixel-major as a tile walks, pixels interleaved (one row's memo shared
    # by all of them, banks claimed back and forth, draws of a pixel that
    # lost its bank), shuffled; without a window also indices past spp
    # (later blocks, other tags); pairs past the tables (sobol.TABLE_PAIRS)
    # and past spp (their own permutations).
    pixels, dims = [0, 1, 4096, 5, 4], range(0, 2 * (max(spp, sobol.TABLE_PAIRS) + 3), 2)
    frac = _WINDOWS[window]
    lo, hi = (0, 2 * spp) if frac is None else (int(frac[0] * spp), max(1, int(frac[1] * spp)))
    walk = [(px, i, d) for px in pixels for i in range(lo, hi) for d in dims]
    interleaved = [(px, i, d) for i in range(lo, hi) for px in pixels for d in dims]
    rng = np.random.default_rng(2)
    for order in (walk, interleaved, [walk[k] for k in rng.permutation(len(walk))]):
        visits = np.asarray(order, np.int64)
        memo = memo_rows(SAMPLER_SOBOL, spp, 1, None if frac is None else (lo, hi))[0]
        assert memo.shape == (sobol.memo_bank_width(spp, frac is not None) * sobol.MEMO_BANKS,)
        out = np.empty((len(visits), 2))
        _sobol_memo_draws(SEED, spp, visits, memo, out)
        plain = np.empty_like(out)
        _sobol_plain_draws(SEED, spp, visits, plain)
        assert np.array_equal(out, plain)
        if order is walk and frac is not None:
            # claimed in order, every bank computed the window's span only
            # and kept the marks of the other positions (sobol.mark_window)
            span = sobol.window_span(spp, lo, hi)
            banks = memo.reshape(sobol.MEMO_BANKS, -1)
            seq = banks[:, 1 + sobol.TABLE_PAIRS:1 + sobol.TABLE_PAIRS + spp]
            assert ((seq < 0).sum(axis=1) == spp - span).all()
            assert span < spp or window == "whole" or spp < 64
    assert memo_rows(SAMPLER_RANDOM, spp, 3).shape == (3, 0)  # other samplers keep none
    assert memo_rows(SAMPLER_SOBOL, 4096, 8192, (0, 4096)).shape == (8192, 0)  # nor a huge unit
    # within the budget at the largest spp, a unit on 32 threads keeps the tables
    tables = sobol.MEMO_BANKS * sobol.memo_bank_width(4096, True)
    assert memo_rows(SAMPLER_SOBOL, 4096, 32, (0, 4096)).shape == (32, tables)
    # over the budget with tables, a unit keeps the entries layout
    over = MEMO_MAX_BYTES // (8 * tables) + 1
    assert memo_rows(SAMPLER_SOBOL, 4096, over, (0, 4096)).shape == (over, 2 * 4096 * sobol.MEMO_BANKS)


def _point_set(p):
    return p[np.lexsort((p[:, 1], p[:, 0]))]


@pytest.mark.parametrize("window", [None, (16, 40)])
def test02_sobol_claim_fills_the_tables_the_bank_last_drew(window):
    # A pixel's claim of a bank fills, ahead of their draws, the pair tables
    # its previous pixel drew (sobol._claim_bank), and only those; the
    # values stay the plain kernel's. Pixels 8 and 12 share bank 0 of 4.
    spp = 64
    lo, hi = (0, spp) if window is None else window
    memo = memo_rows(SAMPLER_SOBOL, spp, 1, (lo, hi))[0]
    bank = memo.reshape(sobol.MEMO_BANKS, -1)[0]
    drawn_pairs = (0, 2, 3, 9)
    first = np.asarray([(8, i, 2 * p) for i in range(lo, hi) for p in drawn_pairs], np.int64)
    _sobol_memo_draws(SEED, spp, first, memo, np.empty((len(first), 2)))
    # the next pixel of the bank draws its film pair only: that claims the bank
    claim = np.asarray([(12, lo, 0)], np.int64)
    _sobol_memo_draws(SEED, spp, claim, memo, np.empty((1, 2)))
    tag = (12 << 20) + 1
    assert bank[0] == tag
    filled = {k for k in range(sobol.TABLE_PAIRS) if bank[1 + k] == tag}
    assert filled == set(drawn_pairs)
    # every pair of the new pixel, filled ahead or at its first draw, reads
    # the plain kernel's values
    rest = np.asarray([(12, i, 2 * p) for i in range(lo, hi) for p in range(12)], np.int64)
    out = np.empty((len(rest), 2))
    _sobol_memo_draws(SEED, spp, rest, memo, out)
    plain = np.empty_like(out)
    _sobol_plain_draws(SEED, spp, rest, plain)
    assert np.array_equal(out, plain)


@pytest.mark.parametrize("name", [n for n in NAMES if n != "uniform"])
def test02_pixels_pairs_and_seeds_differ(name):
    # As sets, not only in order: a shuffled copy of one pattern is still one pattern.
    base = _point_set(points(name, SEED, 0, 16, 0))
    assert not np.array_equal(base, _point_set(points(name, SEED, 1, 16, 0)))  # another pixel
    assert not np.array_equal(base, _point_set(points(name, SEED + 1, 0, 16, 0)))  # another seed
    assert not np.array_equal(base, _point_set(points(name, SEED, 0, 16, 2)))  # another pair
    # and the pairs of one pixel are not the same sequence in the same order
    a, b = points(name, SEED, 0, 64, 0), points(name, SEED, 0, 64, 2)
    assert abs(np.corrcoef(a[:, 0], b[:, 0])[0, 1]) < 0.5


def test02_uniform_is_the_same_grid_in_every_pixel():
    grid = points("uniform", SEED, 0, 16, 0)
    for pixel in (1, 2, 999):
        assert np.array_equal(points("uniform", SEED + pixel, pixel, 16, 0), grid)
    # past pair 0 it is the random sampler
    assert np.array_equal(points("uniform", SEED, 5, 16, 2), points("random", SEED, 5, 16, 2))


# -- 03 per-sampler properties ------------------------------------------------------------

@pytest.mark.parametrize("spp,nx,ny", [(16, 4, 4), (12, 3, 4), (5, 2, 3), (2, 1, 2)])
def test03_uniform_regular_grid(spp, nx, ny):
    expected = np.array([((i % nx + 0.5) / nx, (i // nx + 0.5) / ny) for i in range(spp)])
    assert np.array_equal(points("uniform", SEED, 4, spp, 0), expected)


@pytest.mark.parametrize("dim", [0, 2, 10])
def test03_jittered_one_sample_per_stratum(dim):
    for pixel in range(4):
        for spp in (1, 4, 16, 64, 100):
            m = math.isqrt(spp)
            assert np.all(_grid_counts(points("jittered", SEED, pixel, spp, dim), m, m) == 1)
        for spp in (2, 3, 5, 7, 12, 50):  # not square: spp distinct cells of nx x ny
            nx = math.isqrt(spp)
            ny = -(-spp // nx)
            counts = _grid_counts(points("jittered", SEED, pixel, spp, dim), nx, ny)
            assert counts.max() == 1 and counts.sum() == spp


@pytest.mark.parametrize("dim", [0, 4])
def test03_nrooks_one_per_row_and_column(dim):
    for pixel in range(4):
        for spp in (1, 5, 16, 37, 64):
            p = points("nrooks", SEED, pixel, spp, dim)
            assert np.all(_grid_counts(p, spp, 1) == 1)
            assert np.all(_grid_counts(p, 1, spp) == 1)


@pytest.mark.parametrize("dim", [0, 2])
def test03_multijitter_strata_and_rooks(dim):
    for pixel in range(4):
        for spp in (4, 16, 64, 3, 5, 12, 50):
            m = math.isqrt(spp)
            n = -(-spp // m)
            p = points("multijitter", SEED, pixel, spp, dim)
            cells = _grid_counts(p, m, n)
            cols = _grid_counts(p, m * n, 1)
            rows = _grid_counts(p, 1, m * n)
            assert cells.max() == 1 and cols.max() == 1 and rows.max() == 1, spp
            if m * m == spp:  # square: exactly one everywhere
                assert cells.min() == 1 and cols.min() == 1 and rows.min() == 1


def test03_hammersley_x_is_i_over_n():
    for pixel in range(3):
        for n in (1, 7, 16, 100):
            # the image plane: x = i / n exactly, the lecture's set
            x = points("hammersley", SEED, pixel, n, 0)[:, 0]
            assert sorted(x) == [i / n for i in range(n)]
            # later pairs: one common shift delta per pixel and pair, x = (i + delta) / n
            p = points("hammersley", SEED, pixel, n, 2)
            column = np.floor(p[:, 0] * n)
            assert sorted(column) == list(range(n))
            assert np.ptp(p[:, 0] * n - column) < 1e-9
    # ... and that shift is uniform over pixels (with none, the estimator is biased)
    shifts = [points("hammersley", SEED, px, 8, 2)[:, 0].min() * 8 for px in range(64)]
    assert 0.4 < np.mean(shifts) < 0.6 and np.ptp(shifts) > 0.8


def test03_hammersley_image_plane_bias_is_minus_half_over_n():
    """Deterministic x = i/N: the mean of u is (N - 1) / (2N), a bias of
    -1/(2N) that vanishes as N grows: biased, and consistent."""
    for n in (4, 16, 64, 256):
        assert np.mean(points("hammersley", SEED, 3, n, 0)[:, 0]) - 0.5 == pytest.approx(-0.5 / n)


def _assert_elementary_intervals(p, m):
    for a in range(m + 1):
        counts = _grid_counts(p, 2 ** a, 2 ** (m - a))
        assert np.all(counts == 1), (m, a)


@pytest.mark.parametrize("name", ["sobol", "hammersley"])
def test03_02_net_in_every_elementary_interval(name):
    for pixel in (0, 1, 500):
        for dim in (0, 2, 8):
            for m in range(0, 9):
                _assert_elementary_intervals(points(name, SEED, pixel, 2 ** m, dim), m)


def test03_sobol_prefix_blocks_are_nets():
    # Indices past spp continue the sequence: samples spp..2spp-1 are the next 2^m points,
    # a (0, m, 2)-net again (progressive rendering keeps the guarantee per block).
    p = points("sobol", SEED, 3, 256, 0, count=512)
    _assert_elementary_intervals(p[:256], 8)
    _assert_elementary_intervals(p[256:], 8)


def test03_halton_one_point_per_box():
    for pixel in (0, 1, 42):
        for dim in (0, 2):
            for i, j in [(1, 1), (2, 1), (1, 2), (3, 2), (2, 3), (4, 3)]:
                n = 2 ** i * 3 ** j
                p = points("halton", SEED, pixel, n, dim)
                assert np.all(_grid_counts(p, 2 ** i, 3 ** j) == 1), (i, j)


# -- 04 quality comparisons ---------------------------------------------------------------

def test04_star_discrepancy_ordering():
    pixels = range(4)
    mean = {name: np.mean([_star_discrepancy(points(name, SEED, px, 256, 0)) for px in pixels])
            for name in ("random", "jittered", "sobol", "hammersley", "halton")}
    assert max(mean["sobol"], mean["hammersley"], mean["halton"]) < mean["jittered"], mean
    assert mean["jittered"] < mean["random"], mean


def test04_star_discrepancy_estimator_is_exact():
    p = points("random", SEED, 0, 24, 0)
    assert _star_discrepancy(p) == pytest.approx(naive.star_discrepancy([tuple(q) for q in p]))


def _low_frequency_power(p, kmax=6):
    k = np.arange(-kmax, kmax + 1)
    kx, ky = np.meshgrid(k, k)
    radius = np.hypot(kx, ky)
    ring = (radius >= 1) & (radius < kmax)
    phase = np.exp(-2j * np.pi * (np.outer(p[:, 0], kx[ring]) + np.outer(p[:, 1], ky[ring])))
    return np.mean(np.abs(phase.sum(axis=0)) ** 2 / len(p))


def test04_bluenoise_table_is_the_deterministic_construction():
    # The sequence is progressive (point n's candidates do not depend on the table size),
    # so a short rebuild must equal the cached table's prefix: no stale or foreign cache.
    assert np.array_equal(bluenoise.build_table(64), bluenoise.TABLE[:64])


def test04_bluenoise_has_little_low_frequency_power():
    # Periodogram of 256 points, rings 1 <= |k| < 6; white noise has mean power 1.
    power = {name: np.mean([_low_frequency_power(points(name, SEED, px, 256, dim))
                            for px in range(8) for dim in (0, 2)])
             for name in ("random", "bluenoise")}
    assert power["bluenoise"] < 0.3 * power["random"], power


_SIGMA, _CX, _CY = 0.2, 0.45, 0.55


def _bump(p):
    return np.exp(-((p[:, 0] - _CX) ** 2 + (p[:, 1] - _CY) ** 2) / (2 * _SIGMA ** 2))


def _bump_integral():
    def axis(c):
        s = _SIGMA * math.sqrt(2)
        return _SIGMA * math.sqrt(math.pi / 2) * (math.erf((1 - c) / s) + math.erf(c / s))
    return axis(_CX) * axis(_CY)


def test04_sobol_integrates_faster_than_random():
    exact = _bump_integral()
    rms = {name: math.sqrt(np.mean([(_bump(points(name, SEED, px, 1024, 2)).mean() - exact) ** 2
                                    for px in range(16)]))
           for name in ("random", "sobol")}
    assert rms["sobol"] < rms["random"] / 10, rms


def test04_sobol_pairs_are_padded():
    # A path reads many pairs at once: sobol's padding gives each pair its own sample
    # order, so two pairs' coarse strata are not visited in step. Integrands that couple
    # pairs 1 and 2 (the light point of one vertex, the BSDF direction of the next):
    # sobol's RMS error over 128 pixels at 64 spp must beat independent sampling's
    # exact RMS, sqrt(Var f / 64). Without padding (every pair in index order) the step's
    # error stays at 1/4 whatever spp: the two top bits flip together.
    spp, pixels = 64, range(128)
    cases = [(lambda a, b: ((a[:, 0] < 0.5) & (b[:, 0] < 0.5)).astype(float), 0.25, 3 / 16),
             (lambda a, b: a[:, 0] * b[:, 1], 0.25, 1 / 9 - 1 / 16)]
    for f, exact, variance in cases:
        errors = [f(points("sobol", SEED, px, spp, 2), points("sobol", SEED, px, spp, 4)).mean()
                  - exact for px in pixels]
        rms = math.sqrt(np.mean(np.square(errors)))
        # 128 squared errors: the RMS estimate's own spread is about 1/sqrt(2 * 128) = 6 %
        assert rms < 0.85 * math.sqrt(variance / spp), (exact, rms)


@pytest.mark.parametrize("name", [n for n in NAMES if n != "uniform"])
def test04_every_sampler_is_unbiased(name):
    # (hammersley's image plane is the deterministic lecture set: checked for its
    # known bias in test03; its later pairs are checked here)
    # f = u + 2 v^2 (integral 7/6) averaged over 256 pixels, for spp 16 and 10 (neither
    # square nor a power of two), dims 0 and 2: within 4 standard errors of random's
    # spread. A sampler that puts its points at cell edges (bias 1/(2 spp) in u) or leaves
    # a strip of cells empty misses by more.
    def estimate(sampler, px, spp, dim):
        p = points(sampler, SEED, px, spp, dim)
        return np.mean(p[:, 0] + 2 * p[:, 1] ** 2)

    pixels = range(256)
    for spp in (16, 10):
        for dim in ((2,) if name == "hammersley" else (0, 2)):
            estimates = [estimate(name, px, spp, dim) for px in pixels]
            spread = np.std([estimate("random", px, spp, dim) for px in pixels])
            error = abs(np.mean(estimates) - 7 / 6)
            assert error < 4 * spread / math.sqrt(len(pixels)), (spp, dim, error)


# -- 05 kernels against the naive references ----------------------------------------------

def test05_sobol_generator_matches_pascal_matrix():
    for i in list(range(64)) + [1000, 65535, 123456789]:
        x, y = naive.sobol_2d(i)
        assert sobol.sobol_bits(i, 0) * 2.0 ** -32 == x
        assert sobol.sobol_bits(i, 1) * 2.0 ** -32 == y


def test05_owen_scramble_is_nested():
    # Output's top k bits depend only on the input's top k bits, bijectively (an Owen
    # scramble permutes every elementary interval's children).
    for seed in (1, 0xDEADBEEF):
        for k in (1, 4, 8):
            tops = [sobol.owen_scramble(t << (32 - k), seed) >> (32 - k) for t in range(2 ** k)]
            assert sorted(tops) == list(range(2 ** k))
            for t in range(2 ** k):  # low bits do not change the top bits
                low = (t << (32 - k)) | (0x9E3779B9 & ((1 << (32 - k)) - 1))
                assert sobol.owen_scramble(low, seed) >> (32 - k) == tops[t]


def test05_halton_matches_naive_radical_inverse():
    key = 0x1234_5678_9ABC_DEF0
    choices = halton.digit_choices3(np.uint64(key))
    perms = [list(halton.PERMS3[(choices // 6 ** k) % 6]) for k in range(halton.DIGITS3)]
    for i in list(range(30)) + [242, 243, 100000]:
        assert halton.radical_inverse3(i, key) == \
            pytest.approx(naive.radical_inverse(i, 3, perms, halton.DIGITS3), abs=1e-15)


def test05_hammersley_matches_naive_set():
    # The kernel's point set, with its shift and digital scramble undone.
    n = 32
    p = points("hammersley", SEED, 6, n, 2)
    cols = np.floor(p[:, 0] * n).astype(int)
    order = np.argsort(cols)
    y = np.round(p[order, 1] * 2.0 ** 32).astype(np.uint64)
    xor = y[0] ^ np.uint64(0)  # index 0's radical inverse is 0, so its y is the scramble
    ref = naive.hammersley(n)
    assert [c / n for c in cols[order]] == [r[0] for r in ref]
    assert [float(v ^ xor) * 2.0 ** -32 for v in y] == [r[1] for r in ref]


def test05_permute_is_a_permutation():
    for n in (1, 2, 3, 7, 16, 100, 1000):
        for key in (0, 1, 0xFFFFFFFF, 0x9E3779B97F4A7C15):
            assert sorted(permute(i, n, np.uint64(key)) for i in range(n)) == list(range(n))
