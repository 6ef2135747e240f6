"""BVH traversal of a packet of rays at once: PACKET lanes per instruction.

A packet is PACKET rays in structure-of-arrays form (one array per ray
component, one element per lane) and a mask of the lanes that trace. The
packet walks the 4-wide BVH (bvh.collapse_wide) together: a child is entered
when its box is hit by any active lane, and a leaf's triangles are tested
against every lane. Each of those tests is one loop over the lanes with no
branch in its body, so LLVM's loop vectorizer turns it into AVX-512 / AVX2
instructions (error_model="numpy" matters here: Python's division check is
a branch that stops the vectorizer). Mitsuba's LLVM backend gets its
throughput the same way, 16 rays per instruction.

It computes exactly what `geometry.intersect_arrays` computes for each lane:
the same slab test (near and far planes chosen by the direction's signs,
t = bound / d - o / d) and the same Moller-Trumbore arithmetic with the same
BARY_EPS, so a lane's hit distance is bit-identical to the single-ray
traversal's (tests/test_renderer_bvh.py test03). Only a tie (two primitives
hit at exactly the same t, as a ray through the edge two triangles share)
may resolve to the other primitive, since the packet visits the tree in
another order.

Measured with bench/traversal.py's rays on one thread (AVX-512, 2026-11-27),
packets of 16 against single rays: cornell-box camera / bounce / shadow
rays 3.6-4x / 2.1-2.3x / 2.8-3.4x, veach-mis 3.3x / 2.0x / 2.1x. On a
100 k-triangle mesh (bench/heavy_mesh.py) camera rays 1.7x and shadow rays
1.15x, but scattered bounce rays 0.7x: a packet of incoherent rays visits
the union of their subtrees. So on a tree of more than SMALL_BVH wide
nodes a packet whose live rays do not all share one direction octant is
traced one ray at a time (bounce rays there: 1.0x).

Tried and not kept: visiting a node's children nearest first for the
packet's first live ray (as single rays do): the per-child bookkeeping cost
more than the pruning saved, 5-20 % slower camera and bounce rays on
cornell-box, mixed on the mesh.

Measured, not built yet (2026-11-27, AVX2 machine, one thread, bench/
traversal.py's cornell-box rays in packets of 16): a float32 copy of this
kernel (boxes rounded outwards, triangles rounded, rays converted per
packet) traces camera, bounce and shadow rays 1.46x / 1.50x / 1.50x as fast
as this float64 one (10.2 / 3.9 / 10.9 M rays/s): a float32 lane takes half
a vector register. The camera and bounce rays found the same primitives,
all of them. Shadow rays need a float32 margin: tmax = d (1 - 1e-9)
(geometry.shadow_ray) rounds to d, so the light's own surface occluded 19 %
of the samples; with d (1 - 1e-5) 0.76 % still did, all of them short
rays (d = 0.1-0.4 in a box from -1 to 1) stopped by the light's own
triangles: float32's error in t grows with the coordinates, not with d, so
the margin has to be absolute (or the sampled light's primitives skipped),
not relative. At about a third of a sample's time in traversal
this is about 1.1x on a whole render. Building it means the single-ray
traversal in float32 too (a lane's hit must stay the one a path traced
alone finds), and the offsets and margins re-derived for float32.

Measured and not kept (2026-11-27, fourth session, AVX-512 machine, Zen 5,
bench/traversal.py's rays, one thread, interleaved pairs of runs): float32
boxes alone, with the triangle tests left in float64 so every hit stays
the float64 one. The boxes were stored float32, each bound moved out by
2^-20 of its magnitude and rounded outwards; each lane's near and far
terms o / d were moved apart by 2^-20 |o / d|, sixteen times the four
roundings of t = bound * inv - o * inv, so the float32 slab test can only
enter more boxes than the exact one. The camera and bounce rays found the
same primitives as float64, every one, on cornell-box, veach-mis and
cornell-mesh. A test aiming rays at vertices and edge midpoints of a soup
moved 9e5 from the origin passed with the slack and failed without it.
Packets, float32 against float64:
- cornell-box camera / bounce / shadow: 1.06-1.11x / 0.97-1.02x / 0.78-0.89x;
- veach-mis: 0.94-1.05x / 0.99-1.10x / 0.99-1.02x;
- cornell-mesh: 1.08-1.10x / 0.90-0.96x / 0.75-0.93x.
Single rays: 0.95-1.00x on camera rays, 0.87-0.95x on bounce rays and
0.67-0.94x on shadow rays.
Two causes:
- Shadow rays: tmax = d (1 - 1e-9) no longer prunes the light's own leaf,
  since a float32 bound cannot tell 1e-9 apart. Every shadow ray now tests
  the light's triangles. A shadow epsilon of 1e-4 (pbrt-v4's) would prune
  it again.
- The rest: on these small trees an incoherent packet opens nearly every
  leaf, so its time goes to the triangle tests, which stayed float64. The
  1.5x of the all-float32 prototype above came from the triangles.
Measured (2026-11-27, fifth session, Intel AVX-512, cornell-box, 32 spp,
one thread, `sobol`): the shadow rays' packets take about a fifth of a
render (left untraced, timing only: 1.11 s -> 0.89-0.92 s), more than
bench/traversal.py's 30 M shadow rays/s would say, since a vertex's shadow
packet holds only the lanes that sampled a light. Tracing a packet with at
most 4 (8) such lanes one ray at a time instead: 0 to +5 % (-1 to -5 %),
not kept. Dropping the triangle test's division (wrong hits, an upper
bound): +12 % bounce and +8 % shadow rays/s; a division-free superset test
with the exact test only for the lanes it passes: 0.72x bounce rays/s
(many lane-triangle pairs pass), not kept.
Measured (2026-11-27, sixth session, AMD EPYC Zen 3, AVX2, the same
render): full shadow packets. Each lane's shadow ray went to a row queue
and was traced sixteen at a time, the clear ones' contributions summed per
item in queue order (so still the same bytes whatever the tiling), and an
item folded once its queued rays were traced: 0 to -2 %, not kept. So
the empty lanes of a vertex's shadow packet are not what that fifth pays
for (the packets' occupancy itself was not measured).
Measured and not kept (2026-11-27, seventh session, AMD EPYC Zen 3,
AVX2, cornell-box, 32 or 64 spp, one or two threads, interleaved runs of
/tmp copies; the films were the same bytes in every variant):
- PACKET = 8 (two ymm registers per value instead of four): 1.7x slower
  (4.30-4.39 s against 2.48-2.70 s at 32 spp; not profiled: a packet's
  node visits are shared by half as many rays); PACKET = 32: within the
  noise or slower (median 2.76 s against 2.68 s at 64 spp, six pairs).
- The triangle test without its division for lanes that miss: the
  barycentric and t numerators compared with |det| (signs made det's),
  the division done only for the lanes a triangle is hit by: 3-5 %
  slower (2.69-2.82 s against 2.59-2.68 s), the extra multiplies cost
  more than the divisions they spare on AVX2.
Measured and not kept (2026-11-27, eighth session, AMD EPYC Zen 5,
AVX-512, cornell-box, 32 spp, one thread, three interleaved pairs of
processes): this kernel's triangle tests in float32 (a float32 copy of
tri_isect, each packet's rays converted once, t compared in float64),
without any of the exactness below, as an upper bound of the speed: 0.88-
0.94 s against 0.86-0.92 s for float64, no gain. On AVX-512 sixteen
float64 lanes are two registers per value, and the whole render is not
bound by them here (on the AVX2 machine above the traversal alone was
1.5x).
Measured and kept (2026-11-28, AMD EPYC Zen 5, one thread, six
interleaved pairs of processes, the same film bytes): the inverse
directions' loop and the any-hit loop over `lanes`, a count known only at
run time, so that LLVM's loop vectorizer takes them (the comment in the
kernel; the kernel's asm went from 60 scalar and 2 vector divisions to 27
and 5, the scalar ones now the fallback when the overlap check fails).
The first loop: cornell-box 64 spp 2.073 -> 2.015 s (-2.8 %, faster in
all six pairs), veach-mis 16 spp -1.1 %; the any-hit loop on top:
cornell-box -0.3 %, veach-mis -3.3 %. The reverse lesson, also measured:
this kernel inlined into the path tracer (kernel_inline) made cornell-box
3.4x slower and veach-mis 1.7x (the same bytes; the asm of that build
was not read). Nor does the trick carry over to integrators/path.py's
loops: its shadow rays' sum made branch-free over `lanes` (a select per
channel) made cornell-box 16 % slower and veach-mis 7 %, cause not
examined; not kept.
Measured and not kept (2026-11-28, fifth session, AMD EPYC Zen 4, whose
AVX-512 runs a 512-bit instruction as two 256-bit halves; cornell-box
and veach-mis 128x128, 64 spp, one thread, six interleaved pairs of
processes):
- the float32 triangle tests of the Zen 5 upper bound above (no
  exactness, hits kept beyond 1e-4): cornell-box +0.4 %, veach-mis
  +0.8 %. Half the vector instructions per triangle buy nothing here
  either, so float32 is not what the traversal waits for.
- two triangles of a leaf per pass over the lanes, the lane's best hit
  kept in a register between them. The idea: the loop's result is a
  masked store (bt[r] = t if ok else bt[r]) that the next triangle's
  compare loads back, and x86 cores forward a masked store's value to a
  later load poorly if at all. The same bytes, +1.6 % and +1.5 % time:
  that wait is not what the traversal pays for.
bench/kernel_profile.py measured where the time goes on that machine:
`packet_intersect` 41 % of a cornell-box render (closest hit 26.5 %,
shadow rays 14.7 %), the rest the shading and the sampler.
What would make float32 triangles exact enough (not built):
- each lane keeps the smallest (t32, prim) pair, primitive id as the tie
  break, so the answer does not depend on the order leaves are visited in
  (packets go depth-first, single rays nearest first);
- box padding at least the triangle test's own widening, with an absolute
  term, so a lane never accepts a triangle its own box test would skip
  (else its answer would depend on its packet mates, and so on the tiling);
- the winner's t recomputed in float64 for the hit point, a float64
  re-trace when that disagrees (self-hits at grazing angles);
- a shadow margin that is absolute, not relative (the prototype above).
Measured and not kept (2026-11-28, the session after, AMD EPYC Zen 4,
cornell-box 128x128, 64 spp, one thread, six to eight interleaved pairs of
processes):
- every primitive tested against every lane, no tree, for scenes of up
  to 48 primitives (cornell-box has 36): +14.6 % time, the same bytes.
  The tree prunes a good part of the triangle tests even for incoherent
  packets, and the triangle tests are what a packet pays for;
- yet fewer operations per triangle test gain nothing: the test
  rewritten with the triangle's normal (det = -d.n, t = (o - a).n / det,
  u and v from c = (o - a) x d; a third fewer multiplies, other last
  bits) +0.6 %; each lane's o / d computed once per call instead of at
  every box, +0.4 % (in a loop of its own; stored in the first loop, the
  three more stores took that loop past LLVM's limit of run-time
  overlap checks and it ran scalar again, +2.5 %).
Measured and kept (the same session and method): a leaf's spheres tested
the way its triangles are, one branch-free loop over the lanes
(geometry.sphere_t: sphere_hit's arithmetic, its early return and its two
candidate distances as masks and selects), where each live lane called
sphere_hit out of line: veach-mis (four sphere lights) -10.9 %,
cornell-caustic (a glass and a mirror sphere) -4.3 %, cornell-box (no
spheres) -0.3 %, the same film bytes on all three.
"""

from __future__ import annotations

import numpy as np

from . import kernel
from .geometry import BARY_EPS, _fmax, _fmin, intersect_arrays, sphere_t

# Lanes per packet: 16 float64 lanes are two AVX-512 registers per value
# (four with AVX2), enough to keep the vector units busy through a node's
# dependency chain.
PACKET = 16
# Wide nodes up to which a packet of incoherent rays still beats single rays:
# the union of their subtrees is most of a small tree anyway. Above it only
# packets whose rays share a direction octant are traced together (camera
# rays, most shadow rays); the others go one by one (module doc).
SMALL_BVH = 64


@kernel
def packet_intersect(boxes, kids, prims, tri, sph, stack, ox, oy, oz, dx, dy, dz,
                     ix, iy, iz, bt, bp, act, any_hit):
    """Trace the lanes r with act[r] != 0: on entry bt[r] is the lane's tmax,
    on return its hit distance (or still tmax) and bp[r] the primitive (or
    -1). With `any_hit` a lane stops at its first hit (shadow rays) and its
    act[r] is cleared; the call returns when every lane has one. ix, iy, iz
    are scratch (the inverse directions)."""
    n_tri = tri.shape[0]
    if kids.shape[0] > SMALL_BVH:
        # a big tree: a packet pays only if its rays head the same way
        signs = -1
        coherent = True
        for r in range(PACKET):
            if act[r] != 0:
                sg = (dx[r] < 0.0) * 4 + (dy[r] < 0.0) * 2 + (dz[r] < 0.0)
                if signs < 0:
                    signs = sg
                elif sg != signs:
                    coherent = False
        if not coherent:
            for r in range(PACKET):
                bp[r] = -1
                if act[r] != 0:
                    t, prim = intersect_arrays(boxes, kids, prims, tri, sph, stack, ox[r], oy[r],
                                               oz[r], dx[r], dy[r], dz[r], bt[r], any_hit)
                    if prim >= 0:
                        bt[r] = t
                        bp[r] = prim
                        if any_hit:
                            act[r] = 0
            return
    # The lane arrays' length (PACKET), read at run time on purpose: a short
    # loop over a trip count LLVM knows (16) is fully unrolled before the
    # loop vectorizer runs, and Numba runs LLVM without the SLP vectorizer
    # that could pack the unrolled copies (NUMBA_SLP_VECTORIZE is 0 by
    # default): these 48 divisions ran one at a time. Over a count known only
    # at run time the loop vectorizer takes the loop, with one check per call
    # that the arrays do not overlap. (The triangle and box loops below are
    # too big to unroll: it takes them either way.) Measured in the module doc.
    lanes = ix.shape[0]
    for r in range(lanes):
        ix[r] = 1.0 / dx[r]
        iy[r] = 1.0 / dy[r]
        iz[r] = 1.0 / dz[r]
        bp[r] = -1
    sp = 0
    item = 0  # the root
    while True:
        if item < 0:
            code = -item - 1
            first = code >> 3
            found = False
            for k in range(first, first + (code & 7)):
                prim = prims[k]
                if prim < n_tri:
                    ax, ay, az = tri[prim, 0], tri[prim, 1], tri[prim, 2]
                    e1x, e1y, e1z = tri[prim, 3], tri[prim, 4], tri[prim, 5]
                    e2x, e2y, e2z = tri[prim, 6], tri[prim, 7], tri[prim, 8]
                    for r in range(PACKET):
                        # geometry.tri_hit, every test as a mask instead of a return
                        px = dy[r] * e2z - dz[r] * e2y
                        py = dz[r] * e2x - dx[r] * e2z
                        pz = dx[r] * e2y - dy[r] * e2x
                        det = e1x * px + e1y * py + e1z * pz
                        inv = 1.0 / det
                        tx, ty, tz = ox[r] - ax, oy[r] - ay, oz[r] - az
                        u = (tx * px + ty * py + tz * pz) * inv
                        qx = ty * e1z - tz * e1y
                        qy = tz * e1x - tx * e1z
                        qz = tx * e1y - ty * e1x
                        v = (dx[r] * qx + dy[r] * qy + dz[r] * qz) * inv
                        t = (e2x * qx + e2y * qy + e2z * qz) * inv
                        ok = ((act[r] != 0) & (det != 0.0) & (u >= -BARY_EPS)
                              & (u <= 1.0 + BARY_EPS) & (v >= -BARY_EPS)
                              & (u + v <= 1.0 + BARY_EPS) & (t > 0.0) & (t < bt[r]))
                        bt[r] = t if ok else bt[r]
                        bp[r] = prim if ok else bp[r]
                        found |= ok
                else:
                    s = prim - n_tri
                    cx, cy, cz, rad = sph[s, 0], sph[s, 1], sph[s, 2], sph[s, 3]
                    for r in range(PACKET):
                        # geometry.sphere_t: branch-free, so that this loop
                        # vectorizes like the triangles' (it called sphere_hit
                        # lane by lane: veach-mis -10.9 %, cornell-caustic
                        # -4.3 % time, the same bytes; module doc)
                        t, hit = sphere_t(cx, cy, cz, rad, ox[r], oy[r], oz[r],
                                          dx[r], dy[r], dz[r], bt[r])
                        ok = (act[r] != 0) & hit
                        bt[r] = t if ok else bt[r]
                        bp[r] = prim if ok else bp[r]
                        found |= ok
                if any_hit and found:
                    left = 0
                    for r in range(lanes):  # (why `lanes`: above)
                        done = bp[r] >= 0
                        act[r] = 0 if done else act[r]
                        left += act[r] != 0
                    if left == 0:
                        return
            if sp == 0:
                return
            sp -= 1
            item = stack[sp]
            continue
        for c in range(4):
            kid = kids[item, c]
            if kid == -1:
                continue  # an empty lane of the wide node
            x0, y0, z0 = boxes[item, c], boxes[item, 4 + c], boxes[item, 8 + c]
            x1, y1, z1 = boxes[item, 12 + c], boxes[item, 16 + c], boxes[item, 20 + c]
            hit = 0
            for r in range(PACKET):
                # geometry._lane: the near plane by the direction's sign
                nx_ = x1 if dx[r] < 0.0 else x0
                fx_ = x0 if dx[r] < 0.0 else x1
                ny_ = y1 if dy[r] < 0.0 else y0
                fy_ = y0 if dy[r] < 0.0 else y1
                nz_ = z1 if dz[r] < 0.0 else z0
                fz_ = z0 if dz[r] < 0.0 else z1
                oix, oiy, oiz = ox[r] * ix[r], oy[r] * iy[r], oz[r] * iz[r]
                lo0 = nx_ * ix[r] - oix
                lo1 = ny_ * iy[r] - oiy
                lo2 = nz_ * iz[r] - oiz
                hi0 = fx_ * ix[r] - oix
                hi1 = fy_ * iy[r] - oiy
                hi2 = fz_ * iz[r] - oiz
                lo = _fmax(_fmax(lo0, lo1), _fmax(lo2, 0.0))
                hi = _fmin(_fmin(hi0, hi1), _fmin(hi2, bt[r]))
                hit |= (act[r] != 0) & (lo <= hi * 1.0000000000000004)
            if hit:
                stack[sp] = kid
                sp += 1
        if sp == 0:
            return
        sp -= 1
        item = stack[sp]
