"""Materials: diffuse (Lambertian), mirror and dielectric (smooth glass);
the glossy rough conductor lives in ggx.py.

Directions follow pbrt: `wo` points away from the surface towards where the
light goes (the camera side), `wi` towards where it comes from. `n` is the
front normal. Diffuse and mirror are one-sided, as in Mitsuba: black unless
both wo and wi are on the front side. The dielectric is two-sided.
"""

import math

from . import kernel, kernel_inline
from .geometry import offset_origin
from .sampling import INV_PI, cosine_hemisphere, to_world

MAT_DIFFUSE, MAT_MIRROR, MAT_DIELECTRIC, MAT_GLOSSY = 0, 1, 2, 3


@kernel
def is_specular(mat_type):
    return mat_type == MAT_MIRROR or mat_type == MAT_DIELECTRIC


@kernel
def diffuse_eval(cos_o, cos_i):
    """(f / albedo, pdf) of the Lambertian lobe for cosines w.r.t. the front
    normal: f = albedo/pi, pdf = cos_i/pi (cosine sampling); 0 off the front."""
    if cos_o <= 0.0 or cos_i <= 0.0:
        return 0.0, 0.0
    return INV_PI, cos_i * INV_PI


@kernel_inline
def diffuse_sample(nx, ny, nz, u1, u2):
    """A cosine-distributed wi on the front side: (wi, cos_i, pdf).
    The throughput weight f cos / pdf is exactly the albedo.

    Inlined at Numba IR level: LLVM kept it out of line in the path
    tracer's kernel, where a call makes the caller save its live floating
    point values around it (the System V ABI keeps no xmm register across
    a call).
    Measured on 2026-11-28 (AMD EPYC Zen 4, cornell-box 128x128, 64 spp,
    one thread, eight interleaved pairs of processes): -1.4 % time, the
    same film bytes; bench/kernel_profile.py had put 8 % of the samples in
    this function out of line."""
    lx, ly, lz = cosine_hemisphere(u1, u2)
    wx, wy, wz = to_world(lx, ly, lz, nx, ny, nz)
    return wx, wy, wz, lz, lz * INV_PI


@kernel
def reflect(dx, dy, dz, nx, ny, nz):
    """Mirror the travelling direction d about n."""
    c = 2.0 * (dx * nx + dy * ny + dz * nz)
    return dx - c * nx, dy - c * ny, dz - c * nz


@kernel
def fresnel_dielectric(cos_i, eta):
    """Unpolarized Fresnel reflectance; cos_i >= 0 on the incident side,
    eta = n_transmitted / n_incident."""
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    if sin2_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin2_t)
    r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return 0.5 * (r_parl * r_parl + r_perp * r_perp)


@kernel
def dielectric_sample(dx, dy, dz, nx, ny, nz, ior, u):
    """Sample reflection or refraction of the travelling direction d at a
    smooth interface, choosing by the Fresnel reflectance.

    Returns (new direction, weight, eta_scale, side): the throughput weight
    (1 for reflection, 1/eta'^2 for refraction: radiance is compressed into a
    smaller solid angle when entering the denser medium, pbrt-v4's
    TransportMode::Radiance), eta'^2 to undo that for Russian roulette, and
    the side of the surface (+1 front, -1 back) the new ray leaves from.
    """
    cos_o = -(dx * nx + dy * ny + dz * nz)
    if cos_o >= 0.0:
        eta, fx, fy, fz = ior, nx, ny, nz
    else:
        eta, fx, fy, fz = 1.0 / ior, -nx, -ny, -nz
        cos_o = -cos_o
    f = fresnel_dielectric(cos_o, eta)
    side_in = 1.0 if (fx * nx + fy * ny + fz * nz) > 0.0 else -1.0
    if u < f:
        rx, ry, rz = reflect(dx, dy, dz, fx, fy, fz)
        return rx, ry, rz, 1.0, 1.0, side_in
    sin2_t = (1.0 - cos_o * cos_o) / (eta * eta)
    cos_t = math.sqrt(max(0.0, 1.0 - sin2_t))
    k = cos_o / eta - cos_t
    tx, ty, tz = dx / eta + k * fx, dy / eta + k * fy, dz / eta + k * fz
    inv = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
    return tx * inv, ty * inv, tz * inv, 1.0 / (eta * eta), eta * eta, -side_in


@kernel_inline
def specular_step(mtype, tint_r, tint_g, tint_b, ior, hx, hy, hz, nx, ny, nz, dx, dy, dz, u):
    """The one continuation through a delta lobe (a mirror, `mtype` MAT_MIRROR,
    or glass), shared by every method that follows specular chains from the
    camera (path tracing, photon mapping's visible points, radiosity's
    display): (new direction, the offset origin it leaves from, throughput
    factor r g b, eta scale). `u` decides reflection or refraction at glass;
    a mirror ignores it (callers draw it only for glass). The one-sided
    mirror's back (cos_o <= 0) is the caller's to stop at."""
    if mtype == MAT_MIRROR:
        rx, ry, rz = reflect(dx, dy, dz, nx, ny, nz)
        ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, 1.0)
        return rx, ry, rz, ox, oy, oz, tint_r, tint_g, tint_b, 1.0
    wx, wy, wz, weight, eta_scale, side = dielectric_sample(dx, dy, dz, nx, ny, nz, ior, u)
    ox, oy, oz = offset_origin(hx, hy, hz, nx, ny, nz, side)
    return wx, wy, wz, ox, oy, oz, weight, weight, weight, eta_scale
