"""The `glossy` material: a rough conductor with a GGX or Beckmann microfacet distribution.

    f, pdf = glossy_eval(0, 0, 1, wox, woy, woz, wix, wiy, wiz, 0.1, 0.3, 0.3, 0.3)[:4]

Model (Walter et al. 2007, "Microfacet Models for Refraction through Rough
Surfaces"; the same as pbrt-v4's TrowbridgeReitzDistribution and Mitsuba 3's
roughconductor with `distribution: ggx` or `beckmann`):

    f(wo, wi) = F(wo.h) D(h) G2(wo, wi) / (4 cos_o cos_i),   h = normalize(wo + wi)

- The roughness argument `alpha` is signed: alpha in (0, 1] is GGX
  (Trowbridge-Reitz) of that alpha, -alpha Beckmann of that alpha (the
  sign is the material's `distribution`, scene.py's mat_param[:, 1]). The
  two differ in their tails: veach-bidir's lamp (Beckmann, alpha 0.25)
  rendered as GGX moved its 8x8 blocks by factors of 0.8 to 1.6 in Mitsuba
  3's renders as in ours (docs/real-scenes.md).
- D: isotropic GGX, or Beckmann exp(-tan^2 / alpha^2) / (pi alpha^2 cos^4).
- G2: Smith's *height-correlated* masking-shadowing, 1 / (1 + L(wo) + L(wi))
  (Heitz 2014, "Understanding the Masking-Shadowing Function"; pbrt-v4's
  choice; Mitsuba uses the separable G1(wo) G1(wi)). It is symmetric in wo
  and wi, so f is reciprocal.
- F: Schlick's approximation, F0 + (1 - F0)(1 - wo.h)^5, with F0 the
  `specular` RGB reflectance (a stand-in for a metal's complex Fresnel).
  Beckmann's L is Walter et al.'s rational fit, the one Mitsuba's G1 uses.
- Sampling: GGX by visible normals (Heitz 2018, "Sampling the GGX
  Distribution of Visible Normals"), pdf(wi) = D_wo(h) / (4 |wo.h|) with
  D_wo(h) = G1(wo) max(0, wo.h) D(h) / cos_o; the throughput weight
  f cos_i / pdf reduces to F G2 / G1(wo). Beckmann by its whole
  distribution D(h) cos_h (tan^2 = -alpha^2 log(1 - u)), pdf(wi) =
  D(h) cos_h / (4 |wo.h|), weight F G2 |wo.h| / (cos_o cos_h): simpler than
  Mitsuba's visible normals, the same expectation, more variance at grazing wo.

Single scattering only: the energy lost to multiple bounces between
microfacets grows with alpha (about 1 % at alpha 0.1, tens of % near 1 at
grazing angles). One-sided, like the diffuse and mirror materials
(bsdf.py's conventions: wo towards the camera, wi towards the light, n the
front normal): black, with pdf 0, unless both directions are strictly on the
front side.
"""

import math

from . import kernel
from .sampling import INV_PI, onb, sincos_turn

__all__ = ["ggx_D", "ggx_lambda", "ggx_G1", "ggx_G2", "beckmann_D", "beckmann_lambda",
           "schlick", "glossy_eval", "glossy_sample"]


@kernel
def ggx_D(cos_h, alpha):
    """GGX normal distribution of a microfacet normal at cosine `cos_h` to n
    (per unit solid angle, normalised so that D(h) cos_h integrates to 1)."""
    if cos_h <= 0.0:
        return 0.0
    a2 = alpha * alpha
    d = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 * INV_PI / (d * d)


@kernel
def ggx_lambda(cos_t, alpha):
    """Smith's Lambda for GGX: (sqrt(1 + alpha^2 tan^2) - 1) / 2."""
    c2 = cos_t * cos_t
    if c2 >= 1.0:
        return 0.0
    tan2 = (1.0 - c2) / c2
    return 0.5 * (math.sqrt(1.0 + alpha * alpha * tan2) - 1.0)


@kernel
def ggx_G1(cos_t, alpha):
    """Smith masking of one direction at cosine `cos_t` (> 0) to n."""
    if cos_t <= 0.0:
        return 0.0
    return 1.0 / (1.0 + ggx_lambda(cos_t, alpha))


@kernel
def ggx_G2(cos_o, cos_i, alpha):
    """Height-correlated Smith masking-shadowing of two front-side directions."""
    if cos_o <= 0.0 or cos_i <= 0.0:
        return 0.0
    return 1.0 / (1.0 + ggx_lambda(cos_o, alpha) + ggx_lambda(cos_i, alpha))


@kernel
def beckmann_D(cos_h, alpha):
    """Beckmann normal distribution (normalised as ggx_D)."""
    if cos_h <= 0.0:
        return 0.0
    c2 = cos_h * cos_h
    a2 = alpha * alpha
    return math.exp((c2 - 1.0) / (c2 * a2)) * INV_PI / (a2 * c2 * c2)


@kernel
def beckmann_lambda(cos_t, alpha):
    """Smith's Lambda for Beckmann, Walter et al.'s rational fit in
    a = 1 / (alpha tan) (exact to 0.35 %; Mitsuba's G1 is 1 / (1 + this))."""
    c2 = cos_t * cos_t
    if c2 >= 1.0:
        return 0.0
    a = cos_t / (alpha * math.sqrt(1.0 - c2))
    if a >= 1.6:
        return 0.0
    return (1.0 - 1.259 * a + 0.396 * a * a) / (3.535 * a + 2.181 * a * a)


@kernel
def _lobe_D(cos_h, alpha):
    """D of the signed roughness `alpha` (module doc)."""
    if alpha < 0.0:
        return beckmann_D(cos_h, -alpha)
    return ggx_D(cos_h, alpha)


@kernel
def _lobe_lambda(cos_t, alpha):
    """Smith's Lambda of the signed roughness `alpha`."""
    if alpha < 0.0:
        return beckmann_lambda(cos_t, -alpha)
    return ggx_lambda(cos_t, alpha)


@kernel
def schlick(cos_h, f0):
    """Schlick's Fresnel approximation for a reflectance f0 at normal incidence."""
    m = 1.0 - cos_h
    m2 = m * m
    return f0 + (1.0 - f0) * (m2 * m2 * m)


@kernel
def glossy_eval(nx, ny, nz, wox, woy, woz, wix, wiy, wiz, alpha, sr, sg, sb):
    """(f_r, f_g, f_b, pdf): the BRDF (no cosine) for specular RGB (sr, sg, sb)
    and signed roughness alpha (module doc), and the solid-angle pdf of
    `glossy_sample` choosing wi. All zero unless both wo and wi lie strictly
    on the front side of the unit normal n."""
    cos_o = wox * nx + woy * ny + woz * nz
    cos_i = wix * nx + wiy * ny + wiz * nz
    if cos_o <= 0.0 or cos_i <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    hx, hy, hz = wox + wix, woy + wiy, woz + wiz
    inv = 1.0 / math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx * inv, hy * inv, hz * inv
    cos_h = hx * nx + hy * ny + hz * nz
    cos_oh = wox * hx + woy * hy + woz * hz
    d = _lobe_D(cos_h, alpha)
    lam_o = _lobe_lambda(cos_o, alpha)
    common = d / (4.0 * cos_o * cos_i * (1.0 + lam_o + _lobe_lambda(cos_i, alpha)))
    if alpha < 0.0:
        pdf = d * cos_h / (4.0 * cos_oh) if cos_oh > 0.0 else 0.0
    else:
        pdf = d / ((1.0 + lam_o) * 4.0 * cos_o)
    return (schlick(cos_oh, sr) * common, schlick(cos_oh, sg) * common,
            schlick(cos_oh, sb) * common, pdf)


@kernel
def glossy_sample(nx, ny, nz, wox, woy, woz, alpha, sr, sg, sb, u1, u2):
    """Sample wi (module doc: GGX's visible normals, Beckmann's whole
    distribution): (wix, wiy, wiz, weight_r, weight_g, weight_b, pdf) with
    weight = f cos_i / pdf. pdf = 0 (and a zero weight) when wo is not
    strictly on the front side or the reflected wi falls below it; the
    caller then ends the path."""
    sx, sy, sz, tx, ty, tz = onb(nx, ny, nz)
    # wo in the local frame (s, t, n)
    lx = wox * sx + woy * sy + woz * sz
    ly = wox * tx + woy * ty + woz * tz
    lz = wox * nx + woy * ny + woz * nz
    if lz <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if alpha < 0.0:
        return _beckmann_sample(sx, sy, sz, tx, ty, tz, nx, ny, nz, lx, ly, lz, -alpha,
                                sr, sg, sb, u1, u2)
    # Heitz 2018: stretch wo to the hemisphere configuration (alpha = 1) ...
    vx, vy, vz = alpha * lx, alpha * ly, lz
    inv = 1.0 / math.sqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx * inv, vy * inv, vz * inv
    lensq = vx * vx + vy * vy
    if lensq > 0.0:
        il = 1.0 / math.sqrt(lensq)
        t1x, t1y, t1z = -vy * il, vx * il, 0.0
    else:
        t1x, t1y, t1z = 1.0, 0.0, 0.0
    t2x, t2y, t2z = vy * t1z - vz * t1y, vz * t1x - vx * t1z, vx * t1y - vy * t1x
    # ... sample the projected area of the visible half of the hemisphere ...
    r = math.sqrt(u1)
    cos_p, sin_p = sincos_turn(u2)
    p1 = r * cos_p
    p2 = r * sin_p
    s = 0.5 * (1.0 + vz)
    p2 = (1.0 - s) * math.sqrt(max(0.0, 1.0 - p1 * p1)) + s * p2
    p3 = math.sqrt(max(0.0, 1.0 - p1 * p1 - p2 * p2))
    mx = p1 * t1x + p2 * t2x + p3 * vx
    my = p1 * t1y + p2 * t2y + p3 * vy
    mz = p1 * t1z + p2 * t2z + p3 * vz
    # ... and unstretch the normal.
    hx, hy, hz = alpha * mx, alpha * my, max(0.0, mz)
    inv = 1.0 / math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx * inv, hy * inv, hz * inv
    cos_oh = lx * hx + ly * hy + lz * hz
    if cos_oh <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    ix, iy, iz = 2.0 * cos_oh * hx - lx, 2.0 * cos_oh * hy - ly, 2.0 * cos_oh * hz - lz
    if iz <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    lam_o = ggx_lambda(lz, alpha)
    pdf = ggx_D(hz, alpha) / ((1.0 + lam_o) * 4.0 * lz)
    g_ratio = (1.0 + lam_o) / (1.0 + lam_o + ggx_lambda(iz, alpha))  # G2 / G1(wo)
    wx = ix * sx + iy * tx + iz * nx
    wy = ix * sy + iy * ty + iz * ny
    wz = ix * sz + iy * tz + iz * nz
    return (wx, wy, wz, schlick(cos_oh, sr) * g_ratio, schlick(cos_oh, sg) * g_ratio,
            schlick(cos_oh, sb) * g_ratio, pdf)


@kernel
def _beckmann_sample(sx, sy, sz, tx, ty, tz, nx, ny, nz, lx, ly, lz, alpha, sr, sg, sb, u1, u2):
    """`glossy_sample` for Beckmann: h from D(h) cos_h in the frame (s, t, n),
    wo = (lx, ly, lz) in that frame."""
    tan2 = -alpha * alpha * math.log(1.0 - u1)
    cos_h = 1.0 / math.sqrt(1.0 + tan2)
    sin_h = math.sqrt(max(0.0, 1.0 - cos_h * cos_h))
    cos_p, sin_p = sincos_turn(u2)
    hx, hy, hz = sin_h * cos_p, sin_h * sin_p, cos_h
    cos_oh = lx * hx + ly * hy + lz * hz
    if cos_oh <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    ix, iy, iz = 2.0 * cos_oh * hx - lx, 2.0 * cos_oh * hy - ly, 2.0 * cos_oh * hz - lz
    if iz <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    pdf = beckmann_D(cos_h, alpha) * cos_h / (4.0 * cos_oh)
    if not pdf > 0.0:  # D underflows far out in the tail
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    g2 = 1.0 / (1.0 + beckmann_lambda(lz, alpha) + beckmann_lambda(iz, alpha))
    k = g2 * cos_oh / (lz * cos_h)
    wx = ix * sx + iy * tx + iz * nx
    wy = ix * sy + iy * ty + iz * ny
    wz = ix * sz + iy * tz + iz * nz
    return (wx, wy, wz, schlick(cos_oh, sr) * k, schlick(cos_oh, sg) * k,
            schlick(cos_oh, sb) * k, pdf)
