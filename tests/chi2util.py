"""Chi-square goodness of fit of direction samplers against their pdfs.

Mitsuba 3's `chi2` method: bin sampled directions on a (cos theta, phi)
grid of odd resolution around the z axis, integrate the pdf over each cell
for the expected counts, pool the cells expected to hold fewer than 5
samples into one, and compare with Pearson's statistic. The p-value is
checked against a significance level Sidak-corrected for the number of
tests in the family.
"""

import numpy as np
from scipy.stats import chi2

COS_BINS, PHI_BINS = 51, 101


def histogram(dirs: np.ndarray) -> np.ndarray:
    """Counts of unit directions (n, 3) on the (cos theta, phi) grid."""
    cos_t = np.clip(dirs[:, 2], -1.0, 1.0)
    phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2 * np.pi)
    h, _, _ = np.histogram2d(cos_t, phi, bins=[COS_BINS, PHI_BINS], range=[[-1, 1], [0, 2 * np.pi]])
    return h


def expected_counts(pdf, n: int, sub: int = 8) -> np.ndarray:
    """n times the integral of pdf(dirs (m, 3)) -> (m,) over every cell, by a
    sub x sub Gauss-Legendre rule per cell (solid angle: d cos theta d phi)."""
    x, w = np.polynomial.legendre.leggauss(sub)
    c_edges = np.linspace(-1, 1, COS_BINS + 1)
    p_edges = np.linspace(0, 2 * np.pi, PHI_BINS + 1)
    c_mid, c_half = (c_edges[1:] + c_edges[:-1]) / 2, (c_edges[1:] - c_edges[:-1]) / 2
    p_mid, p_half = (p_edges[1:] + p_edges[:-1]) / 2, (p_edges[1:] - p_edges[:-1]) / 2
    cos_t = (c_mid[:, None] + c_half[:, None] * x[None, :])  # (C, sub)
    phi = (p_mid[:, None] + p_half[:, None] * x[None, :])  # (P, sub)
    ct = cos_t[:, None, :, None]
    ph = phi[None, :, None, :]
    st = np.sqrt(np.maximum(0.0, 1 - ct * ct))
    dirs = np.stack(np.broadcast_arrays(st * np.cos(ph), st * np.sin(ph), ct), axis=-1)
    values = pdf(dirs.reshape(-1, 3)).reshape(COS_BINS, PHI_BINS, sub, sub)
    weights = w[:, None] * w[None, :]
    integral = (values * weights).sum(axis=(2, 3)) * c_half[:, None] * p_half[None, :]
    return n * integral


def chi2_pvalue(observed: np.ndarray, expected: np.ndarray) -> float:
    """Pearson's test with cells expected below 5 pooled into one."""
    obs, exp = observed.ravel(), expected.ravel()
    small = exp < 5
    o = np.append(obs[~small], obs[small].sum())
    e = np.append(exp[~small], exp[small].sum())
    keep = e > 0
    if np.any(o[~keep] > 0):
        return 0.0  # samples where the pdf says none can be
    o, e = o[keep], e[keep]
    stat = np.sum((o - e) ** 2 / e)
    return float(chi2.sf(stat, len(e) - 1))


def sidak(alpha: float, tests: int) -> float:
    return 1 - (1 - alpha) ** (1 / tests)
