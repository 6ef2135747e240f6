"""The per-pixel fold and the film store of every tile loop (the loop itself
and why it is written this way: renderer/integrators/tile.py). Inline
kernels: they compile to the same instructions as the loop written out.
"""

from __future__ import annotations

from . import kernel_inline

__all__ = ["add_sample", "add_block", "n_samples", "store_pixel"]


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
