"""The per-pixel fold and the film store of every tile loop (the loop itself
and why it is written this way: renderer/integrators/tile.py). Inline
kernels: they compile to the same instructions as the loop written out.
"""

from __future__ import annotations

from . import kernel_inline

__all__ = ["add_sample", "add_block", "n_samples", "store_pixel", "add_aov_sample",
           "add_aov_block", "store_aov"]


@kernel_inline
def add_sample(sr, sg, sb, tr, tg, tb, r, g, b):
    """One sample's value into a block's sums of values and of squares."""
    return sr + r, sg + g, sb + b, tr + r * r, tg + g * g, tb + b * b


@kernel_inline
def add_block(ar, ag, ab, qr, qg, qb, sr, sg, sb, tr, tg, tb):
    """A block's sums into the pixel's (blocks in canonical order)."""
    return ar + sr, ag + sg, ab + sb, qr + tr, qg + tg, qb + tb


@kernel_inline
def n_samples(blocks):
    """The samples the blocks hold."""
    n = 0
    for bi in range(blocks.shape[0]):
        n += blocks[bi, 1] - blocks[bi, 0]
    return n


@kernel_inline
def store_pixel(out_sum, out_sq, out_w, row, c, ar, ag, ab, qr, qg, qb, n):
    """A pixel's sums into the unit's film arrays at (row, column) of the tile."""
    out_sum[row, c, 0] = ar
    out_sum[row, c, 1] = ag
    out_sum[row, c, 2] = ab
    out_sq[row, c, 0] = qr
    out_sq[row, c, 1] = qg
    out_sq[row, c, 2] = qb
    out_w[row, c] = n


# AOVs (film.py, "AOVs") take the same fold through a row's scratch `scr`:
# scr[0:A] the block's sums, scr[A:2A] the pixel's (A = film.AOV_CHANNELS = 7:
# albedo RGB, normal XYZ, depth); both start at zero and end at zero.

@kernel_inline
def add_aov_sample(scr, ar, ag, ab, nx, ny, nz, depth):
    """One sample's AOVs into the block's sums."""
    scr[0] += ar
    scr[1] += ag
    scr[2] += ab
    scr[3] += nx
    scr[4] += ny
    scr[5] += nz
    scr[6] += depth


@kernel_inline
def add_aov_block(scr):
    """The block's AOV sums into the pixel's (blocks in canonical order)."""
    for i in range(7):
        scr[7 + i] += scr[i]
        scr[i] = 0.0


@kernel_inline
def store_aov(out_aov, row, c, scr):
    """The pixel's AOV sums into the unit's film at (row, column) of the tile."""
    for i in range(7):
        out_aov[row, c, i] = scr[7 + i]
        scr[7 + i] = 0.0
