"""The vertex records of BDPT's subpaths (kernels/subpaths.py) and the BSDF
at a surface vertex: one float64 row per vertex, fields V_* below.

A surface vertex holds what kernels/shading.py's `shade_hit` found there,
so every strategy evaluates the BSDF with the hit's own shading normal and
texture values: BSDFs are evaluated in the shading frame (V_NS) and are 0
where a direction lies behind the geometric normal (V_N).
"""

import math

from . import kernel
from .bsdf import MAT_DIFFUSE, MAT_GLOSSY, diffuse_eval
from .ggx import glossy_eval

# Vertex record fields.
V_P = 0  # position xyz 0..2
V_N = 3  # front normal 3..5 (0 for the camera and point lights: not on a surface)
V_BETA = 6  # throughput rgb 6..8
V_PDF_FWD = 9
V_PDF_REV = 10
V_TYPE = 11
V_DELTA = 12  # sampled by a specular lobe
V_MAT = 13
V_LIGHT = 14  # light index (light vertices, emitting surfaces) or -1
V_WO = 15  # 15..17 unit direction towards the previous vertex of its subpath
V_DLIGHT = 18  # 1 on a point light's vertex (delta position)
# What kernels/shading.py's shade_hit found at a surface vertex: V_N holds its
# geometric normal on the side the BSDF shades (turned to the shading normal's
# side, or to the viewer's for a twosided material), V_NS the shading normal,
# V_ALB the colour input and V_ALPHA the roughness (textures evaluated),
# V_FRONT +1 if V_N is the emitting side, -1 if it was turned away from it.
V_NS = 19  # 19..21
V_ALB = 22  # 22..24
V_ALPHA = 25
V_FRONT = 26
NV = 27
T_CAMERA, T_LIGHT, T_SURFACE = 0.0, 1.0, 2.0


@kernel
def _on_surface(V, i):
    return V[i, V_N] != 0.0 or V[i, V_N + 1] != 0.0 or V[i, V_N + 2] != 0.0


@kernel
def _convert(V, i, pdf, j):
    """Solid-angle pdf at vertex i towards vertex j -> area density at j."""
    wx, wy, wz = V[j, 0] - V[i, 0], V[j, 1] - V[i, 1], V[j, 2] - V[i, 2]
    d2 = wx * wx + wy * wy + wz * wz
    if d2 == 0.0:
        return 0.0
    if _on_surface(V, j):
        inv = 1.0 / math.sqrt(d2)
        pdf *= abs(V[j, V_N] * wx + V[j, V_N + 1] * wy + V[j, V_N + 2] * wz) * inv
    return pdf / d2


@kernel
def _bsdf_f_pdf(mat_type, V, i, wox, woy, woz, wix, wiy, wiz):
    """(f rgb, pdf of sampling wi given wo) of surface vertex i's material in
    its shading frame; 0 for specular ones (delta lobes are never evaluated)
    and where wo or wi lies behind the geometric normal."""
    mt = mat_type[int(V[i, V_MAT])]
    if mt != MAT_DIFFUSE and mt != MAT_GLOSSY:
        return 0.0, 0.0, 0.0, 0.0
    gx, gy, gz = V[i, V_N], V[i, V_N + 1], V[i, V_N + 2]
    if wox * gx + woy * gy + woz * gz <= 0.0 or wix * gx + wiy * gy + wiz * gz <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    nx, ny, nz = V[i, V_NS], V[i, V_NS + 1], V[i, V_NS + 2]
    if mt == MAT_DIFFUSE:
        f, pdf = diffuse_eval(wox * nx + woy * ny + woz * nz, wix * nx + wiy * ny + wiz * nz)
        return V[i, V_ALB] * f, V[i, V_ALB + 1] * f, V[i, V_ALB + 2] * f, pdf
    return glossy_eval(nx, ny, nz, wox, woy, woz, wix, wiy, wiz, V[i, V_ALPHA],
                       V[i, V_ALB], V[i, V_ALB + 1], V[i, V_ALB + 2])


@kernel
def shading_cos(V, i, wx, wy, wz, importance):
    """|w . ns| at surface vertex i for a connection along w, times Veach's
    adjoint correction |wo.ns| |w.ng| / (|wo.ng| |w.ns|) on a light subpath
    (`importance`); wo is the vertex's V_WO."""
    c = abs(V[i, V_NS] * wx + V[i, V_NS + 1] * wy + V[i, V_NS + 2] * wz)
    if importance and (V[i, V_NS] != V[i, V_N] or V[i, V_NS + 1] != V[i, V_N + 1]
                       or V[i, V_NS + 2] != V[i, V_N + 2]):
        wog = abs(V[i, V_N] * V[i, V_WO] + V[i, V_N + 1] * V[i, V_WO + 1]
                  + V[i, V_N + 2] * V[i, V_WO + 2])
        if wog == 0.0:
            return 0.0
        wos = abs(V[i, V_NS] * V[i, V_WO] + V[i, V_NS + 1] * V[i, V_WO + 1]
                  + V[i, V_NS + 2] * V[i, V_WO + 2])
        return wos * abs(V[i, V_N] * wx + V[i, V_N + 1] * wy + V[i, V_N + 2] * wz) / wog
    return c


@kernel
def _connectible(mat_type, V, i):
    if V[i, V_TYPE] != T_SURFACE:
        return True
    mt = mat_type[int(V[i, V_MAT])]
    return mt == MAT_DIFFUSE or mt == MAT_GLOSSY


@kernel
def _dir(V, i, j):
    wx, wy, wz = V[j, 0] - V[i, 0], V[j, 1] - V[i, 1], V[j, 2] - V[i, 2]
    d2 = wx * wx + wy * wy + wz * wz
    if d2 == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    inv = 1.0 / math.sqrt(d2)
    return wx * inv, wy * inv, wz * inv, d2


@kernel
def vertex_f(mat_type, mat_rgb, mat_param, V, i, j):
    """BSDF of surface vertex i scattering between its previous vertex (wo)
    and vertex j (rgb). Reciprocal BSDFs: the same in both transport modes."""
    wx, wy, wz, d2 = _dir(V, i, j)
    if d2 == 0.0:
        return 0.0, 0.0, 0.0
    fr, fg, fb, pdf = _bsdf_f_pdf(mat_type, V, i, V[i, V_WO], V[i, V_WO + 1], V[i, V_WO + 2],
                                  wx, wy, wz)
    return fr, fg, fb
