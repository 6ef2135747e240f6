"""Slow, obviously correct references for the sampler kernels (stumpy's naive.py habit).

Plain Python integers, digit by digit, straight from the definitions; the
tests compare the kernels with these.
"""

from __future__ import annotations

from math import comb


def radical_inverse(i: int, base: int, perms: list[list[int]] | None = None,
                    digits: int | None = None) -> float:
    """Phi_b(i) = sum_k perm_k(a_k(i)) b^-(k+1); `digits` fixes the number of digits used
    (needed when perm_k(0) != 0, else the trailing zeros count)."""
    total, scale, k = 0.0, 1.0 / base, 0
    while (digits is None and i > 0) or (digits is not None and k < digits):
        digit = i % base
        if perms is not None:
            digit = perms[k][digit]
        total += digit * scale
        i //= base
        scale /= base
        k += 1
    return total


def sobol_2d(i: int, bits: int = 32) -> tuple[float, float]:
    """Sobol' dims 0 and 1 at index i: generator matrices identity and Pascal mod 2.

    Output digit r (weight 2^-(r+1)) of dim 1 is sum_k C(k, r) a_k(i) mod 2.
    """
    a = [(i >> k) & 1 for k in range(bits)]
    x = sum(a[r] * 2.0 ** -(r + 1) for r in range(bits))
    y = sum((sum(comb(k, r) * a[k] for k in range(bits)) % 2) * 2.0 ** -(r + 1)
            for r in range(bits))
    return x, y


def hammersley(n: int) -> list[tuple[float, float]]:
    """The unscrambled Hammersley set (i/n, Phi_2(i))."""
    return [(i / n, radical_inverse(i, 2)) for i in range(n)]


def star_discrepancy(points: list[tuple[float, float]]) -> float:
    """Exact 2D star discrepancy by brute force over anchored boxes, O(n^3).

    The supremum of |#(P in [0,a)x[0,b))/n - ab| is reached with a, b among
    the point coordinates and 1, counting the box open (undercount) or
    closed (overcount).
    """
    n = len(points)
    xs = sorted({p[0] for p in points} | {1.0})
    ys = sorted({p[1] for p in points} | {1.0})
    worst = 0.0
    for a in xs:
        for b in ys:
            closed = sum(1 for x, y in points if x <= a and y <= b)
            open_ = sum(1 for x, y in points if x < a and y < b)
            worst = max(worst, closed / n - a * b, a * b - open_ / n)
    return worst
