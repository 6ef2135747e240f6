"""Warps from the unit square to directions and points, with their pdfs.

Conventions: directions are unit vectors; solid-angle pdfs; a local frame
(s, t, n) is built around a unit normal with Duff et al.'s branchless ONB.
"""

import math

from . import kernel

INV_PI = 1.0 / math.pi


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
    """Shirley-Chiu concentric map of [0,1)^2 to the unit disk."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    if a == 0.0 and b == 0.0:
        return 0.0, 0.0
    if abs(a) > abs(b):
        r, phi = a, (math.pi / 4) * (b / a)
    else:
        r, phi = b, math.pi / 2 - (math.pi / 4) * (a / b)
    return r * math.cos(phi), r * math.sin(phi)


@kernel
def cosine_hemisphere(u1, u2):
    """Local direction with pdf cos(theta)/pi (Malley's method)."""
    x, y = concentric_disk(u1, u2)
    z = math.sqrt(max(0.0, 1.0 - x * x - y * y))
    return x, y, z


@kernel
def uniform_hemisphere(u1, u2):
    """Local direction with pdf 1/(2 pi)."""
    z = u1
    r = math.sqrt(max(0.0, 1.0 - z * z))
    phi = 2.0 * math.pi * u2
    return r * math.cos(phi), r * math.sin(phi), z


@kernel
def uniform_sphere(u1, u2):
    """Direction with pdf 1/(4 pi)."""
    z = 1.0 - 2.0 * u1
    r = math.sqrt(max(0.0, 1.0 - z * z))
    phi = 2.0 * math.pi * u2
    return r * math.cos(phi), r * math.sin(phi), z


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
