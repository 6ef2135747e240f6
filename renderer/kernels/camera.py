"""The pinhole camera as a sensor: projection, importance We and its pdfs.

    fx, fy, we, cos_cam, dist, wx, wy, wz = camera_connect(cam, 64, 64, px, py, pz)

`cam` is `scene.camera_array(camera, width, height)`: origin, right, up,
forward (unit vectors), tan of the half field of view along x and y. The film
sits on the plane at distance 1 along `forward`, covering
[-tx, tx] x [-ty, ty] (area A = 4 tx ty); film position (fx, fy) in pixels,
x right and row 0 at the top, exactly as `camera_ray` (below) maps it to a
direction.

Importance, pbrt-v3 PerspectiveCamera::We / Pdf_We / Sample_Wi style, but
normalised *per pixel* rather than per film: a pixel covers A / (W H) of the
plane, so the importance of direction w (cos = w . forward) is

    We = W H / (A cos^4)        (0 outside the film or behind the camera)

and a light path's splat We cos_cam / dist^2 (times the light side's
throughput) estimates the pixel's mean radiance, the quantity a camera sample
of path tracing estimates. The directional pdf of a camera ray drawn
uniformly over the film is pdf_dir = 1 / (A cos^3) (solid angle; the
pinhole's positional pdf is 1): BDPT's MIS uses this one, per film, as pbrt
does, so the t = 1 strategy's density (one light path per camera sample)
and the camera rays' densities are compared on the same footing.
"""

import math

import numpy as np

from . import kernel


@kernel
def camera_ray(cam, width, height, fx, fy):
    """World-space direction through film position (fx, fy) (pixels, row 0 at top)."""
    sx = (2.0 * fx / width - 1.0) * cam[12]
    sy = (1.0 - 2.0 * fy / height) * cam[13]
    dx = sx * cam[3] + sy * cam[6] + cam[9]
    dy = sx * cam[4] + sy * cam[7] + cam[10]
    dz = sx * cam[5] + sy * cam[8] + cam[11]
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    return dx * inv, dy * inv, dz * inv


@kernel
def film_area(cam):
    """A: the film's area on the plane at distance 1."""
    return 4.0 * cam[12] * cam[13]


@kernel
def camera_project(cam, width, height, dx, dy, dz):
    """Film position (fx, fy) of the unit direction d leaving the camera and
    its cosine to `forward`: (ok, fx, fy, cos). ok is False behind the camera
    or outside the film."""
    cos = dx * cam[9] + dy * cam[10] + dz * cam[11]
    if cos <= 0.0:
        return False, 0.0, 0.0, cos
    sx = (dx * cam[3] + dy * cam[4] + dz * cam[5]) / (cos * cam[12])
    sy = (dx * cam[6] + dy * cam[7] + dz * cam[8]) / (cos * cam[13])
    fx = (sx + 1.0) * 0.5 * width
    fy = (1.0 - sy) * 0.5 * height
    if not (0.0 <= fx < width and 0.0 <= fy < height):
        return False, fx, fy, cos
    return True, fx, fy, cos


@kernel
def camera_we(cam, width, height, dx, dy, dz):
    """(We, fx, fy): the per-pixel importance of the unit direction d leaving
    the camera (module doc) and where it lands on the film; We = 0 off film."""
    ok, fx, fy, cos = camera_project(cam, width, height, dx, dy, dz)
    if not ok:
        return 0.0, fx, fy
    c2 = cos * cos
    return width * height / (film_area(cam) * c2 * c2), fx, fy


@kernel
def camera_pdf_dir(cam, width, height, dx, dy, dz):
    """Solid-angle pdf of a camera ray uniform over the film taking the unit
    direction d: 1 / (A cos^3), 0 off the film (pbrt's Pdf_We)."""
    ok, fx, fy, cos = camera_project(cam, width, height, dx, dy, dz)
    if not ok:
        return 0.0
    return 1.0 / (film_area(cam) * cos * cos * cos)


@kernel
def camera_connect(cam, width, height, px, py, pz):
    """Connect the world point p to the pinhole (pbrt's Sample_Wi):
    (fx, fy, We, cos_cam, dist, wx, wy, wz) with w the unit direction from p
    to the camera. We = 0 when p is off the film (or at the pinhole). The
    splat of a light subpath vertex is beta f |cos_p| We cos_cam / dist^2,
    times visibility."""
    wx, wy, wz = cam[0] - px, cam[1] - py, cam[2] - pz
    dist = math.sqrt(wx * wx + wy * wy + wz * wz)
    if dist == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0
    inv = 1.0 / dist
    wx, wy, wz = wx * inv, wy * inv, wz * inv
    we, fx, fy = camera_we(cam, width, height, -wx, -wy, -wz)
    cos = -(wx * cam[9] + wy * cam[10] + wz * cam[11])
    return fx, fy, we, cos, dist, wx, wy, wz
