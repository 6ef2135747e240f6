"""renderer.lab, the estimator lab's statistics: the exact Student t tail it
uses, and a bias test that passes unbiased renders at its stated rate and
catches a small systematic error; the convergence slope and its verdicts."""

from __future__ import annotations

import numpy as np
import pytest

from renderer.lab import (ALPHA, P_CRITICAL, Render, bias_test, binomial_tail, block_means,
                          config_report, level_report, t_two_sided_p)


@pytest.mark.parametrize("nu", [1, 2, 3, 4, 5, 6, 7, 10, 15])
def test01_the_t_tail_is_students(nu):
    from scipy import stats

    t = np.array([0.0, 0.3, 1.0, 2.0, 3.5, 10.0, 100.0, -2.0])
    np.testing.assert_allclose(t_two_sided_p(t, nu), 2 * stats.t.sf(np.abs(t), nu),
                               rtol=1e-9, atol=1e-15)
    assert t_two_sided_p(np.array([np.inf]), nu)[0] == 0.0


def _renders(rng, truth, runs, noise, shift=0.0, skew=False):
    out = []
    for _ in range(runs):
        if skew:  # a skewed per-pixel estimator (exponential), as at low spp
            image = truth * rng.exponential(1.0, truth.shape)
        else:
            image = truth + noise * rng.standard_normal(truth.shape)
        out.append(image + shift)
    return out


@pytest.mark.parametrize("runs", [2, 4, 8])
def test02_unbiased_renders_pass_at_the_stated_rate(runs):
    # 300 experiments of R renders of a 64 x 64 image (64 blocks); exact reference.
    rng = np.random.default_rng(runs)
    truth = rng.uniform(0.2, 1.0, (64, 64, 3))
    tests = [bias_test(_renders(rng, truth, runs, 0.3), truth, np.zeros_like(truth), 8)
             for _ in range(300)]
    counts = np.array([t["biased_blocks"] for t in tests])
    # Each block is significant with probability ALPHA: the counts are Binomial(64, ALPHA).
    assert abs(counts.mean() - 64 * ALPHA) < 4 * np.sqrt(64 * ALPHA * (1 - ALPHA) / 300)
    assert np.mean([not t["unbiased"] for t in tests]) < 0.02  # false alarms are rare


def test03_skewed_low_spp_renders_pass_on_block_means():
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.2, 1.0, (32, 32, 3))
    tests = [bias_test(_renders(rng, truth, 4, 0, skew=True), truth, np.zeros_like(truth), 8)
             for _ in range(200)]
    assert np.mean([not t["unbiased"] for t in tests]) < 0.03


def test03b_one_firefly_block_is_not_bias():
    # Heavy tails: one block's repeats caught a rare, huge contribution. Its t is
    # enormous, but it is one block of 16, not a systematic error.
    rng = np.random.default_rng(11)
    truth = rng.uniform(0.2, 1.0, (32, 32, 3))
    renders = _renders(rng, truth, 4, 0.1)
    renders[0][3, 3] += 500.0
    test = bias_test(renders, truth, np.zeros_like(truth), 8)
    assert test["unbiased"] and test["biased_blocks"] <= 2


def test04_a_two_percent_bias_is_caught_and_the_reference_noise_counts():
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.2, 1.0, (32, 32, 3))
    biased = bias_test(_renders(rng, truth, 4, 0.1, shift=0.02 * truth.mean()), truth,
                       np.zeros_like(truth), 8)
    assert not biased["unbiased"] and biased["bias_p"] < P_CRITICAL
    assert biased["relative_bias"] == pytest.approx(0.02, abs=0.005)
    # A noisy reference (its variance given) is no reason to call renders biased.
    ref_var = np.full_like(truth, 0.05 ** 2)
    noisy_ref = truth + 0.05 * rng.standard_normal(truth.shape)
    tests = [bias_test(_renders(rng, truth, 4, 0.1), noisy_ref, ref_var, 8) for _ in range(100)]
    assert np.mean([not t["unbiased"] for t in tests]) < 0.05


def test04b_the_binomial_tail_is_exact():
    from scipy import stats

    for k, n in ((0, 16), (3, 16), (5, 16), (16, 16), (7, 64)):
        assert binomial_tail(k, n, ALPHA) == pytest.approx(stats.binom.sf(k - 1, n, ALPHA),
                                                           rel=1e-9)
    assert binomial_tail(5, 16, ALPHA) < P_CRITICAL < binomial_tail(4, 16, ALPHA)


def test05_levels_and_slopes():
    rng = np.random.default_rng(5)
    truth = rng.uniform(0.2, 1.0, (16, 16, 3))
    spps = [1, 4, 16, 64]
    mc = [level_report([Render(r, 1.0 * s) for r in _renders(rng, truth, 6, 0.4 / np.sqrt(s))],
                       truth, np.zeros_like(truth), 8) for s in spps]
    assert [lv["rmse"] for lv in mc] == sorted((lv["rmse"] for lv in mc), reverse=True)
    assert mc[0]["variance"] == pytest.approx(0.16, rel=0.15)
    assert mc[0]["mse"] == pytest.approx(0.16, rel=0.15)  # the reference is exact
    assert mc[0]["efficiency"] == pytest.approx(1 / (mc[0]["mse"] * 1.0))
    report = config_report(spps, mc)
    assert report["slope"] == pytest.approx(-0.5, abs=0.05)
    assert report["consistent"] and report["unbiased"]
    # An estimator whose error levels off at its bias: inconsistent, biased.
    flat = [level_report([Render(r, 1.0) for r in _renders(rng, truth, 6, 0.4 / np.sqrt(s),
                                                          shift=0.1)],
                         truth, np.zeros_like(truth), 8) for s in spps]
    report = config_report(spps, flat)
    assert not report["consistent"] and not report["unbiased"]
    assert flat[-1]["bias2"] == pytest.approx(0.01, rel=0.2)
    # Biased, but the bias shrinks as spp grows (photon mapping's radius): consistent.
    shrinking = [level_report([Render(r, 1.0) for r in _renders(rng, truth, 6, 0.4 / np.sqrt(s),
                                                               shift=0.2 / s ** 0.25)],
                              truth, np.zeros_like(truth), 8) for s in spps]
    report = config_report(spps, shrinking)
    assert not report["unbiased"] and report["consistent"]


def test06_block_means_need_a_whole_block():
    assert block_means(np.ones((10, 12, 3)), 4).shape == (2, 3, 3)
    with pytest.raises(ValueError, match="smaller than one"):
        block_means(np.ones((3, 12, 3)), 4)
