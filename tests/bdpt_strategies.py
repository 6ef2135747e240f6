"""A test helper for BDPT's MIS (moved out of the renderer): every strategy's
weight for one complete path, recomputed from scratch in plain Python over
the kernels of renderer/kernels/subpaths.py."""

from __future__ import annotations

import numpy as np

from renderer.kernels.bsdf import MAT_DIELECTRIC, MAT_MIRROR
from renderer.kernels.lights import LIGHT_POINT
from renderer.kernels.subpaths import (NV, T_LIGHT, T_SURFACE, V_DELTA, V_LIGHT, V_MAT,
                                       V_PDF_FWD, V_PDF_REV, V_TYPE, mis_weight,
                                       pdf_light_origin, vertex_pdf, workspace)


def strategy_weights(sc, cam, width, height, depth, heuristic, V, s, t):
    """MIS weights of every strategy for the complete path that strategy (s, t)
    of the subpaths in V forms (a test helper, plain Python over the kernels).

    The path x_0 (light) .. x_{n-1} (camera), n = s + t, is re-cut as each
    strategy (s', t') would have sampled it: the subpath rows are rebuilt
    with the forward and reverse densities the random walks store, then
    `mis_weight` evaluates (s', t'). Returns (weights, rebuilt) where
    weights[s'] is the weight (0 for strategies that cannot sample this
    path: s' = 0 with a point light, a connection at a specular vertex,
    (1, 1)) and rebuilt is the workspace of the cut (s, t) itself, to compare
    with the random walks' own densities.
    """
    n = s + t
    lrow, srow = depth + 2, 2 * (depth + 2)
    P = np.zeros((n, NV))
    for i in range(s):
        P[i] = V[srow if (s == 1 and i == 0) else lrow + i]
    for i in range(t):
        P[n - 1 - i] = V[i]
    light_index = int(P[0, V_LIGHT])
    point = sc.light_type[light_index] == LIGHT_POINT
    specular = [P[i, V_TYPE] == T_SURFACE and sc.mat_type[int(P[i, V_MAT])]
                in (MAT_MIRROR, MAT_DIELECTRIC) for i in range(n)]
    mt, mr, mp, lt, la = sc.mat_type, sc.mat_rgb, sc.mat_param, sc.light_type, sc.light_area
    weights = np.zeros(n + 1)
    rebuilt = None
    for s2 in range(0, n):
        t2 = n - s2
        if n > 2 and s2 == 1 and t2 == 1:
            continue
        if n == 2 and s2 != 0:
            continue
        if s2 == 0 and point:
            continue
        if s2 >= 1 and (specular[s2 - 1] or specular[s2]):
            continue
        W = workspace(depth)
        rows = []  # (row of W, index into P)
        for i in range(t2):
            rows.append((i, n - 1 - i))
        for i in range(s2):
            rows.append((srow if (s2 == 1 and i == 0) else lrow + i, i))
        for row, k in rows:
            W[row] = P[k]
            W[row, V_PDF_FWD] = W[row, V_PDF_REV] = W[row, V_DELTA] = 0.0
            if k == 0 and row < lrow:  # the light point reached by the camera subpath
                W[row, V_TYPE] = T_SURFACE
                W[row, V_MAT] = 0.0
            elif k == 0:
                W[row, V_TYPE] = T_LIGHT
            if W[row, V_TYPE] == T_SURFACE and specular[k]:
                W[row, V_DELTA] = 1.0
        cam_row = list(range(t2))
        light_row = [srow if (s2 == 1 and i == 0) else lrow + i for i in range(s2)]
        for sub in (cam_row, light_row):
            for i, row in enumerate(sub):
                if i == 0:
                    if sub is light_row:
                        W[row, V_PDF_FWD] = pdf_light_origin(lt, la, W, row)
                    continue
                before = sub[i - 2] if i >= 2 else -1
                W[row, V_PDF_FWD] = vertex_pdf(mt, mr, mp, lt, la, cam, width, height, W,
                                               sub[i - 1], before, row)
            for i, row in enumerate(sub):
                if i + 2 <= len(sub) - 1:  # the walk sampled on from sub[i + 1]
                    W[row, V_PDF_REV] = vertex_pdf(mt, mr, mp, lt, la, cam, width, height, W,
                                                   sub[i + 1], sub[i + 2], row)
        weights[s2] = mis_weight(sc, cam, width, height, W, lrow, srow, s2, t2, heuristic)
        if s2 == s:
            rebuilt = W
    return weights, rebuilt
