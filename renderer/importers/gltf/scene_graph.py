"""The scene graph: the scene's node trees with their world transforms,
cameras and KHR_lights_punctual lights."""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from ...scene_format import MAX_COORDINATE, MAX_RADIANCE
from .reader import _Reader, _show

# glTF gives point lights in candela (lm/sr); rayfarm's point intensity is
# radiant (W/sr). 683 lm/W is the luminous efficacy the photometric units are
# defined by (and Blender's glTF exporter and importer use).
POINT_CANDELA_PER_WATT_SR = 683.0

MAX_NODE_DEPTH = 128  # levels of the node hierarchy
DEFAULT_LONG_SIDE = 512  # pixels along the longer side of the image
DEFAULT_FOV = 40.0  # degrees, the framing camera's field of view


class _SceneGraph(_Reader):
    # -- nodes --------------------------------------------------------------

    def scene_roots(self) -> tuple[list[int], str]:
        scenes = self.array("scenes")
        if not scenes:
            raise self.fail("the file has no scenes: nothing to render", "/scenes")
        si = self.index(self.gltf, "scene", "", "scenes")
        if si is None:
            si = 0
        s, sptr = self.item("scenes", si)
        nodes = self.get(s, "nodes", sptr, "list", default=[])
        roots = [self._node_ref(v, f"{sptr}/nodes/{k}") for k, v in enumerate(nodes)]
        if not roots:
            raise self.fail("the scene has no nodes: nothing to render", sptr)
        return roots, sptr

    def _node_ref(self, v: Any, ptr: str) -> int:
        n = len(self.array("nodes"))
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v < n:
            raise self.fail(f"expected a node index in [0, {n}), got {_show(v)}", ptr)
        return v

    def walk(self, roots: list[int], sptr: str):
        """(node, world matrix, pointer) for every node under the roots, parents
        first. The hierarchy must be a forest of strict trees: a node with two
        parents, a root with a parent, or a cycle is refused."""
        nodes = self.array("nodes")
        parent: dict[int, int] = {}
        for i, raw in enumerate(nodes):
            ptr = f"/nodes/{i}"
            n = self.obj(raw, ptr)
            for k, c in enumerate(self.get(n, "children", ptr, "list", default=[])):
                c = self._node_ref(c, f"{ptr}/children/{k}")
                if c in parent or c == i:
                    raise self.fail(f"node {c} has two parents (nodes {parent.get(c, i)} and "
                                    f"{i}): the node hierarchy must be a set of trees (a cycle?)",
                                    f"{ptr}/children/{k}")
                parent[c] = i
        seen: set[int] = set()
        for k, r in enumerate(roots):
            if r in parent:
                raise self.fail(f"root node {r} is also a child of node {parent[r]}: the node "
                                "hierarchy must be a set of trees (a cycle?)", f"{sptr}/nodes/{k}")
            if r in seen:
                raise self.fail(f"root node {r} is listed twice", f"{sptr}/nodes/{k}")
            seen.add(r)
        stack = [(r, np.eye(4), 1) for r in reversed(roots)]
        while stack:
            i, parent_world, depth = stack.pop()
            ptr = f"/nodes/{i}"
            if depth > MAX_NODE_DEPTH:
                raise self.fail(f"the node hierarchy is more than {MAX_NODE_DEPTH} levels deep",
                                ptr)
            n = self.obj(nodes[i], ptr)
            world = parent_world @ self.local_matrix(n, ptr)
            yield i, world, ptr
            children = self.get(n, "children", ptr, "list", default=[])
            stack.extend((c, world, depth + 1) for c in reversed(children))

    def local_matrix(self, n: dict, ptr: str) -> np.ndarray:
        if "matrix" in n:
            m = np.asarray(self.numbers(n, "matrix", ptr, 16, [], -MAX_COORDINATE,
                                        MAX_COORDINATE)).reshape(4, 4).T  # column-major
            if not np.allclose(m[3], [0, 0, 0, 1]):
                raise self.fail("the last row of a node matrix must be [0, 0, 0, 1]",
                                f"{ptr}/matrix")
            if any(k in n for k in ("translation", "rotation", "scale")):
                self.note(ptr, "translation/rotation/scale ignored: the node also gives a "
                          "matrix, which is used")
            return m
        t = self.numbers(n, "translation", ptr, 3, [0, 0, 0], -MAX_COORDINATE, MAX_COORDINATE)
        q = self.numbers(n, "rotation", ptr, 4, [0, 0, 0, 1], -1.0001, 1.0001)
        s = self.numbers(n, "scale", ptr, 3, [1, 1, 1], -MAX_COORDINATE, MAX_COORDINATE)
        norm = math.sqrt(sum(c * c for c in q))
        if not abs(norm - 1) < 1e-3:
            raise self.fail(f"rotation must be a unit quaternion (its length is {norm:.6g})",
                            f"{ptr}/rotation")
        x, y, z, w = (c / norm for c in q)
        r = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        m = np.eye(4)
        m[:3, :3] = r * np.asarray(s)[None, :]
        m[:3, 3] = t
        return m

    # -- cameras, lights ------------------------------------------------------

    def camera(self, c: dict, cptr: str, world: np.ndarray, nptr: str) -> dict:
        p = self.obj(self.get(c, "perspective", cptr, "obj", required=True), f"{cptr}/perspective")
        pptr = f"{cptr}/perspective"
        yfov = self.number(p, "yfov", pptr, 0.0, 0, math.pi)
        if not math.radians(1e-3) <= yfov <= math.radians(179):
            raise self.fail(f"yfov must lie in (0, pi) radians, got {yfov:g}", f"{pptr}/yfov")
        aspect = self.get(p, "aspectRatio", pptr, "number")
        if aspect is not None and not 1e-3 <= aspect <= 1e3:
            raise self.fail(f"aspectRatio must lie in [0.001, 1000], got {aspect:g}",
                            f"{pptr}/aspectRatio")
        width, height = _resolution(aspect or 1.0)
        if aspect is None:
            self.note(pptr, f"no aspectRatio: the image is square ({width}x{height})")
        self.note(pptr, "znear/zfar ignored: rayfarm does not clip")
        return {"type": "perspective", "to_world": _camera_to_world(world, self, nptr),
                "fov": math.degrees(yfov), "fov_axis": "y", "width": width, "height": height}

    def default_camera(self, shapes: list[dict]) -> dict:
        lo = np.min([s["_bounds"][0] for s in shapes], axis=0)
        hi = np.max([s["_bounds"][1] for s in shapes], axis=0)
        centre = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        distance = radius / math.sin(math.radians(DEFAULT_FOV) / 2)
        m = np.eye(4)
        m[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # looks along -z, +x to the right of the image
        m[:3, 3] = centre + [0.0, 0.0, distance]
        width, height = _resolution(1.0)
        return {"type": "perspective", "to_world": m.tolist(), "fov": DEFAULT_FOV,
                "fov_axis": "smaller", "width": width, "height": height}

    def punctual_lights(self) -> dict[int, Callable]:
        ext = self.extension(self.gltf, "", "KHR_lights_punctual")
        if ext is None:
            return {}
        xptr = "/extensions/KHR_lights_punctual"
        out = {}
        for i, raw in enumerate(self.get(ext, "lights", xptr, "list", default=[])):
            lptr = f"{xptr}/lights/{i}"
            light = self.obj(raw, lptr)
            ltype = self.get(light, "type", lptr, "str", required=True)
            if ltype not in ("point", "spot", "directional"):
                raise self.fail(f"unknown light type {ltype!r}", f"{lptr}/type")
            colour = self.numbers(light, "color", lptr, 3, [1, 1, 1], 0, 1)
            intensity = self.number(light, "intensity", lptr, 1.0, 0, math.inf)
            radiant = np.asarray(colour) * intensity / POINT_CANDELA_PER_WATT_SR
            if "range" in light:
                self.number(light, "range", lptr, 1.0, 0, math.inf)
                self.note(lptr, "range ignored: the light falls off with the inverse square "
                          "everywhere")
            out[i] = self.light_factory(ltype, radiant, lptr)
        return out

    def light_factory(self, ltype: str, radiant: np.ndarray, lptr: str) -> Callable:
        def place(world: np.ndarray, nptr: str) -> dict | None:
            if ltype == "directional":
                self.note(lptr, "ignored: rayfarm has no directional light yet")
                return None
            if ltype == "spot":
                self.note(lptr, "spot light approximated as a point light (its cone is "
                          "ignored)")
            if radiant.max() > MAX_RADIANCE:
                raise self.fail(f"intensity of {radiant.max():g} W/sr exceeds "
                                f"{MAX_RADIANCE:g}", lptr)
            position = world[:3, 3]
            if np.any(np.abs(position) > MAX_COORDINATE):
                raise self.fail(f"the light lies beyond +-{MAX_COORDINATE:g}", nptr)
            if radiant.max() <= 0:
                return None
            return {"type": "point", "position": [float(x) for x in position],
                    "intensity": [float(c) for c in radiant]}
        return place



def _resolution(aspect: float) -> tuple[int, int]:
    """(width, height) with the longer side DEFAULT_LONG_SIDE pixels."""
    if aspect >= 1:
        return DEFAULT_LONG_SIDE, max(1, round(DEFAULT_LONG_SIDE / aspect))
    return max(1, round(DEFAULT_LONG_SIDE * aspect)), DEFAULT_LONG_SIDE


def _camera_to_world(world: np.ndarray, imp: _Reader, nptr: str) -> list[list[float]]:
    """The Mitsuba-convention sensor matrix (looks along local +z, +y up, +x to
    the left) of a glTF camera node (looks along local -z, +y up, +x to the
    right): the node's rotation and translation, turned half a turn about y.
    Scale is dropped (it does not change a pinhole's picture); a mirror stays."""
    a = world[:3, :3]
    q, r = np.linalg.qr(a)
    q = q * np.sign(np.diag(r))[None, :]  # columns of `a`, orthonormalised in order
    scales = np.linalg.norm(a, axis=0)
    if not np.allclose(a, q * scales[None, :], atol=1e-6 * max(scales.max(), 1e-300)):
        imp.note(nptr, "the camera node's transform shears: its rotation part is used")
    m = np.eye(4)
    m[:3, :3] = q @ np.diag([-1.0, 1.0, -1.0])
    m[:3, 3] = world[:3, 3]
    return m.tolist()
