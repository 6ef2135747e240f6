"""Warps from the unit square to directions and points, with their pdfs.

Conventions: directions are unit vectors; solid-angle pdfs; a local frame
(s, t, n) is built around a unit normal with Duff et al.'s branchless ONB.
"""

import math

from . import kernel

INV_PI = 1.0 / math.pi
ONE_MINUS_EPS = 1.0 - 2.0 ** -53  # the largest float64 below 1: where [0, 1) ends

# Minimax polynomials of sin and cos on [-pi/4, pi/4], the coefficients of
# fdlibm's __kernel_sin and __kernel_cos (Sun Microsystems, 1993): with them
# both are within about an ulp there.
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


@kernel
def sincos_quarter(th):
    """(cos th, sin th) for |th| <= pi/4, by the polynomials above.

    Why not math.cos and math.sin: libm's calls, each with its own range
    reduction, were about 8 % of a cornell-box sample's time (one pair per
    diffuse bounce, in the concentric map; measured by replacing them with
    a cheap approximation), and the concentric map needs them only on a
    quarter turn, where a polynomial is exact to about an ulp (tested
    against libm). Measured on 2026-11-27 (Intel AVX-512, cornell-box,
    32 spp, one thread, interleaved runs): +3 to +6 % samples/s; the films
    differ from libm's in the last bits. Measured and not kept
    (2026-11-28, AMD EPYC Zen 4, cornell-box 128x128, 64 spp, one thread,
    six interleaved pairs of processes): the polynomials by Estrin's
    scheme, half the dependent steps of Horner's and within an ulp of libm
    too, -0.4 % time, inside the noise, and other last bits."""
    z = th * th
    s = th + th * z * (_S1 + z * (_S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))))
    r = z * z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6)))))
    return 1.0 - (0.5 * z - r), s


@kernel
def sincos_turn(u):
    """(cos 2 pi u, sin 2 pi u) for u in [0, 1): the quarter turn nearest u
    (4u rounded, exact in binary) and `sincos_quarter` of what is left,
    rotated by that many quarter turns. For the full-turn angles of the
    samplers (uniform sphere and hemisphere, the sphere light's cone, GGX's
    visible normals), which called libm's cos and sin: on veach-mis (four
    sphere lights, glossy plates) about 7 % of a render's samples landed in
    libm (bench/kernel_profile.py, Intel Xeon, 2026-11-29). The error is
    the quarter turn's plus one rounding of the reduced angle: about an ulp
    of the angle (tested against libm)."""
    x = 4.0 * u
    q = math.floor(x + 0.5)
    c, s = sincos_quarter((x - q) * (0.5 * math.pi))
    k = int(q) & 3
    if k == 0:
        return c, s
    if k == 1:
        return -s, c
    if k == 2:
        return -c, -s
    return s, -c


@kernel
def onb(nx, ny, nz):
    """Two unit tangents (s, t) completing the unit normal n to a frame
    (Duff et al. 2017, "Building an Orthonormal Basis, Revisited")."""
    sign = math.copysign(1.0, nz)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return (1.0 + sign * nx * nx * a, sign * b, -sign * nx,
            b, sign + ny * ny * a, -ny)


@kernel
def to_world(lx, ly, lz, nx, ny, nz):
    sx, sy, sz, tx, ty, tz = onb(nx, ny, nz)
    return (lx * sx + ly * tx + lz * nx,
            lx * sy + ly * ty + lz * ny,
            lx * sz + ly * tz + lz * nz)


@kernel
def concentric_disk(u1, u2):
    """Shirley-Chiu concentric map of [0,1)^2 to the unit disk.

    Which of |a| and |b| is larger is a coin flip for every sample, so a
    branch on it is mispredicted half the time. The octant's numerator and
    denominator are picked with selects instead (LLVM emits blends), and
    one ratio goes through the polynomials: phi = pi/4 b/a when |a| > |b|,
    else phi = pi/2 - th with th = pi/4 a/b (cos phi = sin th, sin phi =
    cos th). The same arithmetic as the two branches, so the same bits.
    Measured on 2026-11-28 (AMD EPYC Zen 4, 128x128, 64 spp, one thread,
    eight interleaved pairs of processes), with `_pick_triangle`'s selects
    as well (kernels/lights.py; of those only the CDF's lower end compiled
    branch-free, and only it is kept): cornell-box -2.6 %, veach-mis
    -1.5 % time, the same film bytes."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    if a == 0.0 and b == 0.0:
        return 0.0, 0.0
    wide = abs(a) > abs(b)
    num = b if wide else a
    den = a if wide else b
    c, s = sincos_quarter((math.pi / 4) * (num / den))
    return den * (c if wide else s), den * (s if wide else c)


@kernel
def cosine_hemisphere(u1, u2):
    """Local direction with pdf cos(theta)/pi (Malley's method).

    z from the disk point's radius (max(|a|, |b|) of concentric_disk), which
    does not wait for the angle's polynomials, instead of from x and y:
    tried on 2026-11-29 (Zen 4, cornell-box 64 spp, one thread), +0.8 %
    time, no gain: the profile's samples after this square root are skid,
    not a stall on it. Not kept."""
    x, y = concentric_disk(u1, u2)
    z = math.sqrt(max(0.0, 1.0 - x * x - y * y))
    return x, y, z


@kernel
def uniform_hemisphere(u1, u2):
    """Local direction with pdf 1/(2 pi)."""
    z = u1
    r = math.sqrt(max(0.0, 1.0 - z * z))
    cos_p, sin_p = sincos_turn(u2)
    return r * cos_p, r * sin_p, z


@kernel
def uniform_sphere(u1, u2):
    """Direction with pdf 1/(4 pi)."""
    z = 1.0 - 2.0 * u1
    r = math.sqrt(max(0.0, 1.0 - z * z))
    cos_p, sin_p = sincos_turn(u2)
    return r * cos_p, r * sin_p, z


@kernel
def uniform_triangle(u1, u2):
    """Barycentrics (b0, b1) uniform over a triangle (pbrt-v4's
    area-preserving square-to-triangle map)."""
    if u1 < u2:
        b0 = u1 / 2.0
        b1 = u2 - b0
    else:
        b1 = u2 / 2.0
        b0 = u1 - b1
    return b0, b1


# Multiple importance sampling heuristics (Veach), by id.
POWER, BALANCE = 0, 1


@kernel
def mis_weight(pa, pb, heuristic):
    """Veach's weight of strategy a against b: power (beta = 2) or balance."""
    if heuristic == BALANCE:
        return pa / (pa + pb)
    return pa * pa / (pa * pa + pb * pb)
