"""What every method knows of a surface at a hit: normals, uv, the material's inputs.

    (fn, g, s, rgb, alpha, mat, light) = shade_hit(sc, prim, hx, hy, hz, dx, dy, dz)

- `fn` is the front geometric normal: the side an area light emits from
  (the triangle's winding, or the sphere's outside; what light sampling uses).
- `s` is the shading normal: the per-vertex normals interpolated at the hit
  (barycentrics recomputed from the hit point), or the geometric normal.
- `g` is the geometric normal of the side the BSDF shades: the front normal,
  turned to the shading normal's side when the triangle has vertex normals
  (the vertex normals say which side is the front, as in Mitsuba and pbrt).
  A `twosided` material seen from the back has `g` and `s` both turned
  towards the viewer, so its back shades as its front (Mitsuba's twosided
  adapter); one-sided materials are black where -d . g <= 0.
- rgb is the colour input (albedo, tint or specular) and alpha the glossy
  roughness, each a constant or a texture evaluated at the hit's uv (a
  scalar input takes the texture's luminance, `tex_value`); alpha is signed,
  negative for a Beckmann lobe (kernels/ggx.py). The opacity is not
  shading's: a hit the mask passes is no hit (kernels/opacity.py).

The callers evaluate BSDFs in the shading frame (cosines against `s`) and
reject a direction that lies on different sides of `g` and `s`, so shading
normals never send light through a surface.

Texture lookups follow Mitsuba 3's bitmap texture: uv' = uv * uv_scale +
uv_offset; uv' (0, 0) is the top-left corner of the image as stored (row 0),
u to the right, v down the rows; wrap mode repeat; bilinear filtering puts
texel centres at (i + 0.5) / W, nearest takes the texel uv' falls in. A
checkerboard is color0 where the fractional parts of u' and v' are both
above 1/2 or both not, color1 elsewhere (Mitsuba 3's checkerboard).
"""

import math

from . import kernel, kernel_inline

TEX_BITMAP, TEX_CHECKER = 0, 1
# tex_info's columns: kind, texel offset, width, height, channels, filter
# (1 bilinear, 0 nearest), uv scale u v, uv offset u v, color0 rgb, color1 rgb
TEX_COLUMNS = 16
MIN_ROUGHNESS = 1e-3  # material_format.MIN_ROUGHNESS: a textured roughness is clamped to it


@kernel_inline
def _texel(data, off, w, c, x, y):
    i = off + (y * w + x) * c
    if c == 1:
        v = data[i]
        return v, v, v
    return data[i], data[i + 1], data[i + 2]


@kernel
def tex_eval(info, data, t, u, v):
    """The RGB of texture t at uv (u, v); a one-channel image is grey."""
    uu = u * info[t, 6] + info[t, 8]
    vv = v * info[t, 7] + info[t, 9]
    if info[t, 0] == TEX_CHECKER:
        if ((uu - math.floor(uu)) > 0.5) == ((vv - math.floor(vv)) > 0.5):
            return info[t, 10], info[t, 11], info[t, 12]
        return info[t, 13], info[t, 14], info[t, 15]
    off, w, h, c = int(info[t, 1]), int(info[t, 2]), int(info[t, 3]), int(info[t, 4])
    if info[t, 5] == 0.0:  # nearest
        x = int(math.floor(uu * w)) % w
        y = int(math.floor(vv * h)) % h
        r, g, b = _texel(data, off, w, c, x, y)
        return float(r), float(g), float(b)
    px = uu * w - 0.5
    py = vv * h - 0.5
    fx0 = math.floor(px)
    fy0 = math.floor(py)
    wx1 = px - fx0
    wy1 = py - fy0
    wx0 = 1.0 - wx1
    wy0 = 1.0 - wy1
    x0 = int(fx0) % w
    y0 = int(fy0) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    r00, g00, b00 = _texel(data, off, w, c, x0, y0)
    r10, g10, b10 = _texel(data, off, w, c, x1, y0)
    r01, g01, b01 = _texel(data, off, w, c, x0, y1)
    r11, g11, b11 = _texel(data, off, w, c, x1, y1)
    return (wy0 * (wx0 * r00 + wx1 * r10) + wy1 * (wx0 * r01 + wx1 * r11),
            wy0 * (wx0 * g00 + wx1 * g10) + wy1 * (wx0 * g01 + wx1 * g11),
            wy0 * (wx0 * b00 + wx1 * b10) + wy1 * (wx0 * b01 + wx1 * b11))


@kernel_inline
def tex_value(info, data, t, u, v):
    """Texture t as a scalar input (roughness, opacity), Mitsuba 3's eval_1:
    the luminance of its RGB, the value of a one-channel image."""
    r, g, b = tex_eval(info, data, t, u, v)
    return 0.212671 * r + 0.715160 * g + 0.072169 * b


@kernel
def _barycentrics(tri, prim, hx, hy, hz):
    """(b1, b2) of the hit point on triangle `prim` (rows of tri_isect: v0, e1, e2)."""
    e1x, e1y, e1z = tri[prim, 3], tri[prim, 4], tri[prim, 5]
    e2x, e2y, e2z = tri[prim, 6], tri[prim, 7], tri[prim, 8]
    wx, wy, wz = hx - tri[prim, 0], hy - tri[prim, 1], hz - tri[prim, 2]
    d00 = e1x * e1x + e1y * e1y + e1z * e1z
    d01 = e1x * e2x + e1y * e2y + e1z * e2z
    d11 = e2x * e2x + e2y * e2y + e2z * e2z
    d20 = wx * e1x + wy * e1y + wz * e1z
    d21 = wx * e2x + wy * e2y + wz * e2z
    den = d00 * d11 - d01 * d01
    if den == 0.0:
        return 0.0, 0.0
    return (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den


@kernel
def _surface_detail(sc, prim, a, need_uv, hx, hy, hz, fx, fy, fz):
    """The slow part of `shade_hit`, out of line: (shading normal, uv) where
    the triangle has vertex data or the material a texture."""
    n_tri = sc.tri_n.shape[0]
    sx, sy, sz = fx, fy, fz
    u, v = 0.0, 0.0
    if prim >= n_tri:  # a sphere: Mitsuba's (phi / 2 pi, theta / pi), in world axes
        s = prim - n_tri
        inv_r = 1.0 / sc.sph[s, 3]
        lx = (hx - sc.sph[s, 0]) * inv_r
        ly = (hy - sc.sph[s, 1]) * inv_r
        lz = (hz - sc.sph[s, 2]) * inv_r
        phi = math.atan2(ly, lx)
        if phi < 0.0:
            phi += 2.0 * math.pi
        u = phi / (2.0 * math.pi)
        v = math.acos(min(1.0, max(-1.0, lz))) / math.pi
        return sx, sy, sz, u, v
    b1, b2 = _barycentrics(sc.tri_isect, prim, hx, hy, hz)
    b0 = 1.0 - b1 - b2
    if a < 0:
        return sx, sy, sz, b1, b2
    an = sc.attr_n
    if an[a, 0] != 0.0 or an[a, 1] != 0.0 or an[a, 2] != 0.0:
        nx = b0 * an[a, 0] + b1 * an[a, 3] + b2 * an[a, 6]
        ny = b0 * an[a, 1] + b1 * an[a, 4] + b2 * an[a, 7]
        nz = b0 * an[a, 2] + b1 * an[a, 5] + b2 * an[a, 8]
        ln = math.sqrt(nx * nx + ny * ny + nz * nz)
        if ln > 1e-12:
            sx, sy, sz = nx / ln, ny / ln, nz / ln
    at = sc.attr_uv
    if need_uv:
        u = b0 * at[a, 0] + b1 * at[a, 2] + b2 * at[a, 4]
        v = b0 * at[a, 1] + b1 * at[a, 3] + b2 * at[a, 5]
    return sx, sy, sz, u, v


@kernel
def hit_uv(sc, prim, hx, hy, hz):
    """The uv of primitive `prim` at the point h on it (as `shade_hit` finds it)."""
    a = sc.tri_attr[prim] if prim < sc.tri_n.shape[0] else -1
    _, _, _, u, v = _surface_detail(sc, prim, a, True, hx, hy, hz, 0.0, 0.0, 1.0)
    return u, v


@kernel_inline
def shade_hit(sc, prim, hx, hy, hz, dx, dy, dz):
    """At the hit point h of primitive `prim` reached along direction d:
    (front normal, geometric normal, shading normal, colour input rgb,
    roughness alpha, material, light); see the module's doc."""
    n_tri = sc.tri_n.shape[0]
    a = -1
    if prim < n_tri:
        fx, fy, fz = sc.tri_n[prim, 0], sc.tri_n[prim, 1], sc.tri_n[prim, 2]
        mat, light = sc.tri_mat[prim], sc.tri_light[prim]
        a = sc.tri_attr[prim]
    else:
        s = prim - n_tri
        inv_r = 1.0 / sc.sph[s, 3]
        if sc.sph_flip[s] != 0:
            inv_r = -inv_r
        fx = (hx - sc.sph[s, 0]) * inv_r
        fy = (hy - sc.sph[s, 1]) * inv_r
        fz = (hz - sc.sph[s, 2]) * inv_r
        mat, light = sc.sph_mat[s], sc.sph_light[s]
    t_col, t_rough = sc.mat_tex[mat, 0], sc.mat_tex[mat, 1]
    need_uv = t_col >= 0 or t_rough >= 0
    gx, gy, gz = fx, fy, fz
    sx, sy, sz = fx, fy, fz
    r, g, b = sc.mat_rgb[mat, 0], sc.mat_rgb[mat, 1], sc.mat_rgb[mat, 2]
    alpha = sc.mat_param[mat, 1]
    if a >= 0 or need_uv:
        sx, sy, sz, u, v = _surface_detail(sc, prim, a, need_uv, hx, hy, hz, fx, fy, fz)
        if gx * sx + gy * sy + gz * sz < 0.0:
            gx, gy, gz = -gx, -gy, -gz
        if t_col >= 0:
            r, g, b = tex_eval(sc.tex_info, sc.tex_data, t_col, u, v)
        if t_rough >= 0:
            # the material's sign is its distribution (ggx.py)
            alpha = math.copysign(min(1.0, max(MIN_ROUGHNESS, tex_value(
                sc.tex_info, sc.tex_data, t_rough, u, v))), alpha)
    if sc.mat_twosided[mat] != 0 and dx * gx + dy * gy + dz * gz > 0.0:
        gx, gy, gz = -gx, -gy, -gz
        sx, sy, sz = -sx, -sy, -sz
    return fx, fy, fz, gx, gy, gz, sx, sy, sz, r, g, b, alpha, mat, light
