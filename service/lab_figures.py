"""An experiment's figures (service.experiments), drawn with matplotlib for
reports and docs, where a static image serves better than the dashboard's
live SVG:

- `plot.png`: RMSE against spp (log-log, with the 1/sqrt(spp) slope of plain
  Monte Carlo for comparison) and the bias test's -log10 p against spp (the
  line at P_CRITICAL separates "unbiased" from "biased");
- `maps.png`: per configuration, at the largest spp, the bias map (the
  repeats' average minus the reference, luminance, on a diverging scale
  symmetric about 0 that covers 99 % of the pixels) and the variance map (per-pixel variance over the
  repeats, luminance, log scale), beside the reference.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np

from renderer.film import tonemap_srgb8
from renderer.lab import P_CRITICAL

__all__ = ["write_figures"]

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _save(fig, path: Path) -> None:
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex}.png")
    try:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_figures(directory: Path, report: list[dict], maps: list[tuple[np.ndarray, np.ndarray]],
                  reference: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")  # no display; safe in a server thread
    from matplotlib.colors import LogNorm, TwoSlopeNorm
    from matplotlib.figure import Figure

    directory.mkdir(parents=True, exist_ok=True)

    fig = Figure(figsize=(10, 4))
    rmse_ax, bias_ax = fig.subplots(1, 2)
    for config in report:
        spps = [level["spp"] for level in config["levels"]]
        rmse_ax.loglog(spps, [level["rmse"] for level in config["levels"]], "o-",
                       label=config["label"])
        bias_ax.semilogx(spps, [-np.log10(max(level["bias_p"], 1e-300))
                                for level in config["levels"]], "o-", label=config["label"])
    first = report[0]["levels"]
    spps = np.array([level["spp"] for level in first], dtype=float)
    if len(spps) > 1:
        guide = first[0]["rmse"] * np.sqrt(spps[0] / spps)
        rmse_ax.loglog(spps, guide, "k--", lw=0.8, label="1/sqrt(spp)")
    rmse_ax.set(xlabel="spp", ylabel="RMSE against the reference", title="Convergence")
    rmse_ax.grid(True, which="both", alpha=0.3)
    rmse_ax.legend(fontsize=8)
    bias_ax.axhline(-np.log10(P_CRITICAL), color="k", ls="--", lw=0.8)
    bias_ax.text(bias_ax.get_xlim()[0], -np.log10(P_CRITICAL), " biased above", va="bottom",
                 fontsize=8)
    bias_ax.set(xlabel="spp", ylabel="-log10 p (significant pixel blocks)", title="Bias test")
    bias_ax.grid(True, which="both", alpha=0.3)
    _save(fig, directory / "plot.png")

    rows = len(report)
    fig = Figure(figsize=(9, 2.8 * rows + 0.4))
    axes = np.atleast_2d(fig.subplots(rows, 3))
    for row, (config, (bias_map, variance_map)) in enumerate(zip(report, maps)):
        ax_ref, ax_bias, ax_var = axes[row]
        ax_ref.imshow(tonemap_srgb8(reference))
        ax_ref.set_title("reference" if row == 0 else "", fontsize=9)
        ax_ref.set_ylabel(config["label"], fontsize=9)
        bias = bias_map @ LUMINANCE
        # The scale covers 99 % of the pixels: the few that see a light would
        # otherwise wash every other pixel out (they are clipped, not hidden).
        limit = float(np.percentile(np.abs(bias), 99)) or float(np.max(np.abs(bias))) or 1.0
        image = ax_bias.imshow(np.clip(bias, -limit, limit), cmap="RdBu_r",
                               norm=TwoSlopeNorm(0.0, -limit, limit))
        ax_bias.set_title(f"bias at {config['levels'][-1]['spp']} spp", fontsize=9)
        fig.colorbar(image, ax=ax_bias, fraction=0.046, pad=0.04)
        variance = variance_map @ LUMINANCE
        positive = variance[variance > 0]
        if positive.size:
            norm = LogNorm(float(positive.min()), float(max(positive.max(), positive.min() * 10)))
            image = ax_var.imshow(np.where(variance > 0, variance, np.nan), cmap="viridis",
                                  norm=norm)
            fig.colorbar(image, ax=ax_var, fraction=0.046, pad=0.04)
        else:
            ax_var.imshow(np.zeros_like(variance), cmap="gray")
        ax_var.set_title("variance over the repeats", fontsize=9)
        for ax in (ax_ref, ax_bias, ax_var):
            ax.set_xticks([])
            ax.set_yticks([])
    _save(fig, directory / "maps.png")
