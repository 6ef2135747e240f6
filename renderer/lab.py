"""The estimator lab's measurement: how biased, how noisy and how consistent
an estimator is, from R independent renders (different seeds) at several spp
levels and a reference image. The one implementation behind the service's
experiments (service/experiments.py, `POST /experiments`) and
bench/methods.py.

Per spp level (`level_report`), over the pixels (RGB):

- **bias**: the average of the R renders against the reference, per block of
  `block` x `block` pixels of luminance (block means are near-normal where
  single pixels at low spp are far too skewed for a t statistic; the R, G
  and B of a block come from the same paths, so they are one test, not
  three): t = (average - reference) / sqrt(spread^2 / R + reference
  variance), with the spread the blocks' sample variance over the repeats,
  so a method whose pixels are correlated (a shared photon map) is judged by
  its real spread. Under "no bias" each t follows Student's t with
  nu = R - 1 degrees of freedom (`t_two_sided_p`, exact for integer nu), so
  about `ALPHA` of the blocks are significant at level `ALPHA` by chance.
  `bias_p` is the binomial probability of at least as many significant
  blocks as were seen: a systematic error (blur, missing light, meshing)
  makes many blocks significant; "unbiased?" is `bias_p` >= `P_CRITICAL` at
  every level. Counting blocks, rather than combining their p-values
  (Fisher), is what keeps a heavy-tailed estimator honest: one block whose
  few repeats missed a rare light path has an enormous t, which Fisher's sum
  took for bias (BSDF-sampled path tracing at 1 spp, measured); here it is
  one block. Works from R = 2.
- **variance**: the per-pixel sample variance over the repeats, averaged over
  the pixels: what one render's error would be without bias.
- **MSE**: each render's mean squared error against the reference, averaged
  over the repeats, less the reference's own variance (which adds to it).
- **time**: the renders' mean seconds; **efficiency** 1 / (MSE x seconds).

- **bias^2**: the squared error of the repeats' average less what its noise
  (variance / R) and the reference's explain: the systematic error's energy.

Per configuration (`config_report`): the log-log slope of RMSE against spp
(over all levels, and over the last step; plain Monte Carlo falls as
spp^-1/2) and the verdicts. "Unbiased?" holds at every level.
"Consistent?": an unbiased estimator is (its variance falls with spp); a
biased one is if its bias^2 still falls at the last step, by at least
`CONSISTENT_BIAS_DROP` (photon mapping's shrinking radius), and not if it
stays (rasterization's missing light). The slope alone cannot tell: at low
spp a biased estimator's noise still falls while its bias hides under it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ALPHA", "P_CRITICAL", "CONSISTENT_BIAS_DROP", "LUMINANCE", "binomial_tail",
           "corrected_mse", "block_means", "t_two_sided_p", "bias_test", "level_report",
           "config_report", "Render"]

ALPHA = 0.05  # a block is significant when its two-sided p-value is below this
P_CRITICAL = 1e-3  # fewer significant blocks than this probability allows: biased
CONSISTENT_BIAS_DROP = 0.75  # a biased estimator's bias^2 at the last level under this x the one before
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709


@dataclass
class Render:
    """One render of an experiment: its mean image (h, w, 3) and its seconds."""
    mean: np.ndarray
    seconds: float


def block_means(image: np.ndarray, block: int) -> np.ndarray:
    """Means over `block` x `block` pixels (the image cropped to whole blocks),
    per channel: (h // block, w // block, channels)."""
    h, w = (image.shape[0] // block) * block, (image.shape[1] // block) * block
    if h == 0 or w == 0:
        raise ValueError(f"the image ({image.shape[1]}x{image.shape[0]}) is smaller than one "
                         f"{block}x{block} block")
    channels = image.shape[2] if image.ndim == 3 else 1
    return image[:h, :w].reshape(h // block, block, w // block, block, channels).mean(axis=(1, 3))


def t_two_sided_p(t: np.ndarray, nu: int) -> np.ndarray:
    """P(|T| >= |t|) for Student's t with integer `nu` >= 1 degrees of freedom:
    the closed forms of Abramowitz & Stegun 26.7.3 (odd nu) and 26.7.4 (even
    nu), in theta = atan(|t| / sqrt(nu)). Infinite t gives 0, NaN gives 1."""
    if nu < 1:
        raise ValueError("a t statistic needs nu >= 1 degrees of freedom")
    t = np.abs(np.asarray(t, dtype=np.float64))
    theta = np.arctan(np.where(np.isfinite(t), t, np.inf) / math.sqrt(nu))
    s, c = np.sin(theta), np.cos(theta)
    c2 = c * c
    if nu % 2 == 1:
        total = np.zeros_like(theta)
        if nu > 1:
            term = np.ones_like(theta)
            total = term.copy()
            for k in range(2, nu - 1, 2):  # 1 + 2/3 c^2 + 2*4/(3*5) c^4 + ...
                term = term * c2 * k / (k + 1)
                total = total + term
            total = s * c * total
        a = 2.0 / math.pi * (theta + total)  # A(t|nu) = P(|T| < t)
    else:
        term = np.ones_like(theta)
        total = term.copy()
        for k in range(1, nu - 2, 2):  # 1 + 1/2 c^2 + 1*3/(2*4) c^4 + ...
            term = term * c2 * k / (k + 1)
            total = total + term
        a = s * total
    p = np.clip(1.0 - a, 0.0, 1.0)
    return np.where(np.isnan(t), 1.0, p)


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(K >= k) for K ~ Binomial(n, p), exactly."""
    return float(min(1.0, sum(math.comb(n, i) * p ** i * (1 - p) ** (n - i)
                              for i in range(max(k, 0), n + 1))))


def _luminance(image: np.ndarray) -> np.ndarray:
    return image @ LUMINANCE if image.ndim == 3 and image.shape[2] == 3 else image


def bias_test(renders: list[np.ndarray], reference: np.ndarray, reference_var: np.ndarray,
              block: int) -> dict:
    """The bias statistics of `renders` (R mean images) against `reference`
    and its per-pixel variance of the mean (module doc). Returns `bias_p`,
    `biased_blocks` of `blocks` (significant at ALPHA), the per-block t map,
    the relative bias of the image mean and `unbiased` (bias_p >= P_CRITICAL)."""
    runs = len(renders)
    if runs < 2:
        raise ValueError("a bias test needs at least 2 renders (the spread over them)")
    stack = np.stack([block_means(_luminance(r)[..., None], block)[..., 0] for r in renders])
    average = stack.mean(axis=0)
    spread = stack.var(axis=0, ddof=1) / runs
    ref_blocks = block_means(_luminance(reference)[..., None], block)[..., 0]
    ref_var = np.where(np.isfinite(reference_var), reference_var, 0.0)
    ref_var = ref_var @ (LUMINANCE ** 2) if ref_var.ndim == 3 and ref_var.shape[2] == 3 else ref_var
    ref_blocks_var = block_means(ref_var[..., None], block)[..., 0] / (block * block)
    denom = spread + ref_blocks_var
    diff = average - ref_blocks
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(denom > 0, diff / np.sqrt(denom), np.where(diff == 0, 0.0, np.inf))
    significant = int((t_two_sided_p(t, runs - 1) < ALPHA).sum())
    p = binomial_tail(significant, t.size, ALPHA)
    ref_mean = float(reference.mean())
    return {"bias_p": p, "biased_blocks": significant, "blocks": int(t.size), "t": t,
            "relative_bias": float(np.mean(renders) / ref_mean - 1.0) if ref_mean else 0.0,
            "unbiased": bool(p >= P_CRITICAL)}


def corrected_mse(images: np.ndarray, reference: np.ndarray,
                  reference_var: np.ndarray) -> tuple[float, float]:
    """(MSE, raw MSE) of `images` (one or a stack) against `reference`: the raw
    mean squared error less the reference's mean variance, which its own noise
    adds to every comparison (infinite variances, of pixels with one sample,
    count as 0)."""
    raw = float(np.mean((images - reference) ** 2))
    ref_var = np.where(np.isfinite(reference_var), reference_var, 0.0)
    return raw - float(ref_var.mean()), raw


def level_report(renders: list[Render], reference: np.ndarray, reference_var: np.ndarray,
                 block: int) -> dict:
    """Bias, variance, MSE, time and efficiency of one spp level (module doc),
    and the per-pixel maps: `bias_map` (average - reference) and
    `variance_map` (sample variance over the repeats), luminance-free RGB."""
    images = [r.mean for r in renders]
    stack = np.stack(images)
    average = stack.mean(axis=0)
    bias = bias_test(images, reference, reference_var, block)
    variance_map = stack.var(axis=0, ddof=1)
    mse, raw_mse = corrected_mse(stack, reference, reference_var)
    seconds = float(np.mean([r.seconds for r in renders]))
    reliable = mse > 0.5 * raw_mse  # the reference's own noise is a small part of it
    # the average's error less what its own noise (variance / R) explains
    bias2 = (corrected_mse(average, reference, reference_var)[0]
             - float(variance_map.mean()) / len(images))
    mse = max(mse, 1e-30)
    return {"bias_p": bias["bias_p"], "biased_blocks": bias["biased_blocks"],
            "block_t": [[round(float(t), 3) if np.isfinite(t) else None for t in row]
                        for row in bias["t"]],
            "unbiased": bias["unbiased"],
            "relative_bias": bias["relative_bias"], "blocks": bias["blocks"],
            "bias2": max(bias2, 0.0),
            "variance": float(variance_map.mean()), "mse": mse, "rmse": math.sqrt(mse),
            "mse_reliable": bool(reliable), "seconds": seconds,
            "efficiency": 1.0 / (mse * seconds) if seconds > 0 else None,
            "bias_map": average - reference, "variance_map": variance_map}


def config_report(spps: list[int], levels: list[dict]) -> dict:
    """The convergence of one configuration over its spp levels (ascending):
    the log-log slope of RMSE against spp over all levels and over the last
    step, and the verdicts."""
    rmse = np.array([max(level["rmse"], 1e-30) for level in levels])
    logs = np.log(np.asarray(spps, dtype=np.float64))
    slope = last = None
    if len(spps) >= 2:
        slope = float(np.polyfit(logs, np.log(rmse), 1)[0])
        last = float(math.log(rmse[-1] / rmse[-2]) / (logs[-1] - logs[-2]))
    unbiased = all(level["unbiased"] for level in levels)
    if unbiased:
        consistent = True
    elif len(levels) < 2:
        consistent = None  # one level cannot show a trend
    else:
        consistent = bool(levels[-1]["bias2"] < CONSISTENT_BIAS_DROP * levels[-2]["bias2"])
    return {"slope": slope, "last_slope": last, "unbiased": unbiased, "consistent": consistent}
