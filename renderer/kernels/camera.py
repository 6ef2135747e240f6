"""The camera as a sensor: projection, lens, reconstruction filter,
importance We and its pdfs.

    fx, fy, we, cos_cam, dist, wx, wy, wz, lx, ly, lz = camera_connect(cam, 64, 64, px, py, pz, lu, lv)

`cam` is `scene.camera_array(camera, width, height)` (layout: the CAM_*
indices below): origin, right, up, forward (unit vectors), tan of the half
field of view along x and y, the thin lens (aperture radius, 0 for a
pinhole, and focus distance) and the filter. The film sits on the plane at
distance 1 along `forward`, covering [-tx, tx] x [-ty, ty] (area A = 4 tx
ty); film position (fx, fy) in pixels, x right and row 0 at the top,
exactly as `camera_ray` (below) maps it to a direction.

Thin lens (Mitsuba 3's `thinlens`, pbrt's PerspectiveCamera with a lens
radius): a camera ray through film position f starts at a point of the lens
disk (radius r, in the plane through the origin perpendicular to `forward`,
drawn by the concentric map) and aims at the point where the pinhole ray
through f meets the focus plane (at `focus_distance` along `forward`).
Points on the focus plane are sharp; r = 0 is the pinhole, the same bits.

Filters, by filter importance sampling (pbrt-v4's FilterSampler without its
table: the inverse CDF is exact here, so every sample weighs 1): a camera
sample of pixel (x, y) sits at (x + 1/2 + dx, y + 1/2 + dy) with dx, dy
drawn independently from the normalised 1D filter g (`filter_sample`), and
its value goes to its own pixel only, so tiles never overlap. The pixel's
expected value is the filtered image, sum over film positions f of
g(fx - x - 1/2) g(fy - y - 1/2) L(f). The box (g = 1 on [-1/2, 1/2)) keeps
the uniform position x + u of before, bit for bit. A tent or Gaussian reaches
beyond the frame: rays may leave through a border of `margin` pixels around
it (CAM_MARGIN), which the projections below count as film.

Importance, pbrt-v3 PerspectiveCamera::We / Pdf_We / Sample_Wi style, but
normalised *per pixel* rather than per film: a pixel covers A / (W H) of the
plane, so the importance of direction w (cos = w . forward) for a box pixel is

    We = W H / (A cos^4)        (0 outside the film or behind the camera)

and a light path's splat We cos_cam / dist^2 (times the light side's
throughput) estimates the pixel's mean radiance, the quantity a camera sample
of path tracing estimates. With a filter, the splat at film position f goes
to every pixel (x, y) whose filter reaches f, times g(fx - x - 1/2)
g(fy - y - 1/2) (`splat_add`): the same expected image as the camera side's
filter importance sampling. With a lens, the point on the lens is sampled
(pdf 1 / (pi r^2) by area) and We carries 1 / (pi r^2) (pbrt-v4's We with
lensArea): the two cancel, so `camera_connect` returns We as above, with
cos and dist taken from the lens point. The directional pdf of a camera ray
drawn uniformly over the film is pdf_dir = 1 / (A cos^3) (solid angle, also
from a lens point: the focus plane's Jacobian cancels); BDPT's MIS uses this
one, per film, as pbrt does, so the t = 1 strategy's density (one light path
per camera sample) and the camera rays' densities are compared on the same
footing (with a filter, the same proxy for every strategy keeps the weights
summing to 1).
"""

import math

import numpy as np

from . import kernel
from .sampling import concentric_disk

# cam[...] layout (scene.camera_array)
CAM_TX, CAM_TY = 12, 13
CAM_LENS = 14  # aperture radius; 0: a pinhole
CAM_FOCUS = 15  # focus distance
CAM_FILTER = 16  # FILTER_*
CAM_FPARAM = 17  # the tent's radius, the Gaussian's standard deviation
CAM_FRADIUS = 18  # the filter's support radius (pixels)
CAM_FNORM = 19  # the 1D filter's integral (the Gaussian's normalisation)
CAM_MARGIN = 20  # pixels beyond the frame the filter reaches: max(0, radius - 1/2)
CAM_SIZE = 21

FILTER_BOX, FILTER_TENT, FILTER_GAUSSIAN = 0, 1, 2


def filter_params(filt: dict) -> list[float]:
    """cam[CAM_FILTER:] for a resolved filter document (scene-format.md)."""
    if filt["type"] == "tent":
        r = float(filt["radius"])
        return [FILTER_TENT, r, r, r, max(0.0, r - 0.5)]
    if filt["type"] == "gaussian":
        s = float(filt["stddev"])
        r = 4.0 * s  # Mitsuba's cut-off
        c = math.exp(-r * r / (2 * s * s))
        norm = s * math.sqrt(2 * math.pi) * math.erf(r / (s * math.sqrt(2))) - 2 * r * c
        return [FILTER_GAUSSIAN, s, r, norm, max(0.0, r - 0.5)]
    return [FILTER_BOX, 0.5, 0.5, 1.0, 0.0]


@kernel
def filter_eval(cam, t):
    """The normalised 1D filter g at offset t (pixels) from a pixel's centre:
    box 1 on [-1/2, 1/2); tent (1 - |t|/r)/r; Gaussian (Mitsuba's, shifted to
    0 at its radius R = 4 stddev) (exp(-t^2/2s^2) - exp(-R^2/2s^2)) / norm."""
    kind = cam[CAM_FILTER]
    if kind == FILTER_TENT:
        r = cam[CAM_FPARAM]
        a = abs(t)
        return (1.0 - a / r) / r if a < r else 0.0
    if kind == FILTER_GAUSSIAN:
        s = cam[CAM_FPARAM]
        rad = cam[CAM_FRADIUS]
        if abs(t) >= rad:
            return 0.0
        k = -0.5 / (s * s)
        return (math.exp(k * t * t) - math.exp(k * rad * rad)) / cam[CAM_FNORM]
    return 1.0 if -0.5 <= t < 0.5 else 0.0


@kernel
def filter_sample(cam, u):
    """An offset t (pixels) from the pixel's centre with density
    `filter_eval`, from u in [0, 1): the exact inverse CDF (the tent's in
    closed form, the Gaussian's by Newton's method kept inside its bracket)."""
    kind = cam[CAM_FILTER]
    if kind == FILTER_TENT:
        r = cam[CAM_FPARAM]
        if u < 0.5:
            return r * (math.sqrt(2.0 * u) - 1.0)
        return r * (1.0 - math.sqrt(2.0 - 2.0 * u))
    if kind == FILTER_GAUSSIAN:
        s = cam[CAM_FPARAM]
        rad = cam[CAM_FRADIUS]
        k = -0.5 / (s * s)
        c = math.exp(k * rad * rad)
        a = 1.0 / (s * math.sqrt(2.0))
        h = s * math.sqrt(0.5 * math.pi)
        e0 = math.erf(rad * a)
        target = u * cam[CAM_FNORM]
        lo, hi = -rad, rad
        t = 0.0
        for _ in range(64):
            f = h * (math.erf(t * a) + e0) - c * (t + rad) - target
            if f > 0.0:
                hi = t
            else:
                lo = t
            d = math.exp(k * t * t) - c
            tn = t - f / d if d > 0.0 else 0.5 * (lo + hi)
            if not lo < tn < hi:
                tn = 0.5 * (lo + hi)
            if abs(tn - t) <= 1e-12 * rad:
                return tn
            t = tn
        return t
    return u - 0.5


@kernel
def film_position(cam, x, y, fu, fv):
    """The film position of a camera sample of pixel (x, y) from its pair
    (fu, fv): x + fu, y + fv for the box (as before filters existed), else
    the pixel's centre plus filter-distributed offsets."""
    if cam[CAM_FILTER] == FILTER_BOX:
        return x + fu, y + fv
    return x + 0.5 + filter_sample(cam, fu), y + 0.5 + filter_sample(cam, fv)


@kernel
def camera_ray(cam, width, height, fx, fy):
    """World-space direction through film position (fx, fy) (pixels, row 0
    at top) from the camera's origin: the pinhole's ray."""
    sx = (2.0 * fx / width - 1.0) * cam[12]
    sy = (1.0 - 2.0 * fy / height) * cam[13]
    dx = sx * cam[3] + sy * cam[6] + cam[9]
    dy = sx * cam[4] + sy * cam[7] + cam[10]
    dz = sx * cam[5] + sy * cam[8] + cam[11]
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    return dx * inv, dy * inv, dz * inv


@kernel
def lens_point(cam, lu, lv):
    """A point on the lens disk from (lu, lv) in [0, 1)^2 (concentric map;
    Mitsuba's aperture point (a, b, 0) in camera space, whose +x is the
    image's left)."""
    a, b = concentric_disk(lu, lv)
    r = cam[CAM_LENS]
    a *= r
    b *= r
    return (cam[0] - a * cam[3] + b * cam[6], cam[1] - a * cam[4] + b * cam[7],
            cam[2] - a * cam[5] + b * cam[8])


@kernel
def camera_ray_at(cam, width, height, fx, fy, lu, lv):
    """The camera ray through film position (fx, fy): (ox, oy, oz, dx, dy,
    dz). A pinhole's starts at the origin (lu, lv unused); a thin lens's at
    the lens point of (lu, lv), aimed at the focus plane (module doc)."""
    dx, dy, dz = camera_ray(cam, width, height, fx, fy)
    if cam[CAM_LENS] <= 0.0:
        return cam[0], cam[1], cam[2], dx, dy, dz
    ox, oy, oz = lens_point(cam, lu, lv)
    k = cam[CAM_FOCUS] / (dx * cam[9] + dy * cam[10] + dz * cam[11])
    ex = cam[0] + k * dx - ox
    ey = cam[1] + k * dy - oy
    ez = cam[2] + k * dz - oz
    inv = 1.0 / math.sqrt(ex * ex + ey * ey + ez * ez)
    return ox, oy, oz, ex * inv, ey * inv, ez * inv


@kernel
def film_area(cam):
    """A: the film's area on the plane at distance 1."""
    return 4.0 * cam[12] * cam[13]


@kernel
def camera_project(cam, width, height, dx, dy, dz):
    """Film position (fx, fy) of the direction d leaving the camera's origin
    and its cosine to `forward` (d a unit vector): (ok, fx, fy, cos). ok is
    False behind the camera or outside the film and its filter's margin."""
    cos = dx * cam[9] + dy * cam[10] + dz * cam[11]
    if cos <= 0.0:
        return False, 0.0, 0.0, cos
    sx = (dx * cam[3] + dy * cam[4] + dz * cam[5]) / (cos * cam[12])
    sy = (dx * cam[6] + dy * cam[7] + dz * cam[8]) / (cos * cam[13])
    fx = (sx + 1.0) * 0.5 * width
    fy = (1.0 - sy) * 0.5 * height
    m = cam[CAM_MARGIN]
    if not (-m <= fx < width + m and -m <= fy < height + m):
        return False, fx, fy, cos
    return True, fx, fy, cos


@kernel
def camera_project_from(cam, width, height, ox, oy, oz, dx, dy, dz):
    """`camera_project` of a ray from (ox, oy, oz), a point of the lens
    (the origin for a pinhole): the film position whose camera ray it is,
    through the point where it meets the focus plane; cos is d's."""
    if cam[CAM_LENS] <= 0.0:
        return camera_project(cam, width, height, dx, dy, dz)
    cos = dx * cam[9] + dy * cam[10] + dz * cam[11]
    if cos <= 0.0:
        return False, 0.0, 0.0, cos
    k = cam[CAM_FOCUS] / cos
    ok, fx, fy, _ = camera_project(cam, width, height, ox + k * dx - cam[0],
                                   oy + k * dy - cam[1], oz + k * dz - cam[2])
    return ok, fx, fy, cos


@kernel
def camera_we(cam, width, height, dx, dy, dz):
    """(We, fx, fy): the per-pixel importance of the unit direction d leaving
    the pinhole (module doc) and where it lands on the film; We = 0 off film."""
    ok, fx, fy, cos = camera_project(cam, width, height, dx, dy, dz)
    if not ok:
        return 0.0, fx, fy
    c2 = cos * cos
    return width * height / (film_area(cam) * c2 * c2), fx, fy


@kernel
def camera_pdf_dir(cam, width, height, ox, oy, oz, dx, dy, dz):
    """Solid-angle pdf of a camera ray from lens point o (the origin for a
    pinhole) uniform over the film taking the unit direction d:
    1 / (A cos^3), 0 off the film (pbrt's Pdf_We)."""
    ok, fx, fy, cos = camera_project_from(cam, width, height, ox, oy, oz, dx, dy, dz)
    if not ok:
        return 0.0
    return 1.0 / (film_area(cam) * cos * cos * cos)


@kernel
def camera_connect(cam, width, height, px, py, pz, lu, lv):
    """Connect the world point p to the camera (pbrt's Sample_Wi): (fx, fy,
    We, cos_cam, dist, wx, wy, wz, lx, ly, lz) with l the camera's point
    (the pinhole, or the lens point of (lu, lv)) and w the unit direction from
    p to it. We = 0 when p is off the film (or at l). The splat of a light
    subpath vertex is beta f |cos_p| We cos_cam / dist^2, times visibility
    (the lens point's pdf cancels its importance: module doc)."""
    lx, ly, lz = cam[0], cam[1], cam[2]
    if cam[CAM_LENS] > 0.0:
        lx, ly, lz = lens_point(cam, lu, lv)
    wx, wy, wz = lx - px, ly - py, lz - pz
    dist = math.sqrt(wx * wx + wy * wy + wz * wz)
    if dist == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, lx, ly, lz
    inv = 1.0 / dist
    wx, wy, wz = wx * inv, wy * inv, wz * inv
    if cam[CAM_LENS] > 0.0:
        ok, fx, fy, cos = camera_project_from(cam, width, height, lx, ly, lz, -wx, -wy, -wz)
        we = 0.0
        if ok:
            c2 = cos * cos
            we = width * height / (film_area(cam) * c2 * c2)
        return fx, fy, we, cos, dist, wx, wy, wz, lx, ly, lz
    we, fx, fy = camera_we(cam, width, height, -wx, -wy, -wz)
    cos = -(wx * cam[9] + wy * cam[10] + wz * cam[11])
    return fx, fy, we, cos, dist, wx, wy, wz, lx, ly, lz


@kernel
def splat_add(splat, cam, fx, fy, r, g, b):
    """Add a light path's contribution at film position (fx, fy) to the
    (H, W, 3) `splat`: to the pixel it falls in for the box; with a filter,
    to every pixel whose filter reaches it, times the pixel's filter weight
    (module doc). Positions off the frame and its margin add nothing."""
    height, width = splat.shape[0], splat.shape[1]
    if cam[CAM_FILTER] == FILTER_BOX:
        if 0.0 <= fx < width and 0.0 <= fy < height:
            ix, iy = int(fx), int(fy)
            splat[iy, ix, 0] += r
            splat[iy, ix, 1] += g
            splat[iy, ix, 2] += b
        return
    rad = cam[CAM_FRADIUS]
    x_lo = max(0, int(math.floor(fx - 0.5 - rad)))
    x_hi = min(width - 1, int(math.floor(fx - 0.5 + rad)) + 1)
    y_lo = max(0, int(math.floor(fy - 0.5 - rad)))
    y_hi = min(height - 1, int(math.floor(fy - 0.5 + rad)) + 1)
    for iy in range(y_lo, y_hi + 1):
        wy = filter_eval(cam, fy - iy - 0.5)
        if wy <= 0.0:
            continue
        for ix in range(x_lo, x_hi + 1):
            w = wy * filter_eval(cam, fx - ix - 0.5)
            if w > 0.0:
                splat[iy, ix, 0] += r * w
                splat[iy, ix, 1] += g * w
                splat[iy, ix, 2] += b * w
