"""Mitsuba shapes as native ones: rectangles, cubes, disks, spheres, mesh
files (as assets), cylinders (as prisms); shape groups and their instances
flattened."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ...assets import asset_digest, encode_mesh
from ...errors import SceneError
from ...meshio import read_mesh
from .values import _Obj
from .xmltree import _Node

MAX_SHAPES = 100_000  # shapes after instances are flattened (each instance copies its group)
CYLINDER_SEGMENTS = 64


class ShapeMapper:
    """Shapes (a base of scene._Importer)."""

    def _track_bounds(self, lo, hi, m: np.ndarray) -> None:
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])], dtype=np.float64)
        self.bounds.append(corners @ m[:3, :3].T + m[:3, 3])

    def _mesh(self, path: Path, fmt: str, shape_index: int, flip_uv: bool) -> tuple:
        """(digest, lo, hi, face normals?, reader's notes) of a mesh file, as an asset."""
        key = (path, fmt, shape_index, flip_uv)
        if key not in self.mesh_cache:
            mesh = read_mesh(path, fmt=fmt, shape_index=shape_index, label=self.rel(path))
            uvs = mesh.uvs
            if flip_uv and uvs is not None:
                uvs = np.array(uvs, dtype=np.float64)
                uvs[:, 1] = 1.0 - uvs[:, 1]
            blob = encode_mesh(mesh.positions, mesh.faces, mesh.normals, uvs)
            digest = asset_digest(blob)
            self.assets[digest] = blob
            pos = np.asarray(mesh.positions)
            self.mesh_cache[key] = (digest, pos.min(axis=0), pos.max(axis=0), mesh.face_normals,
                                    list(mesh.notes))
        return self.mesh_cache[key]

    def shape(self, node: _Node) -> list[dict]:
        self.enter(node)
        try:
            return self._shape(node)
        finally:
            self.map_stack.pop()

    def _shape(self, node: _Node) -> list[dict]:
        obj = _Obj(self, node)
        t = obj.type
        m = obj.transform("to_world")
        if t == "shapegroup":
            shapes = [s for ch in obj.children("shape") for s in self.shape(ch)]
            self.groups[id(node)] = shapes
            obj.finish(("shape",))
            return []
        if t == "instance":
            refs = obj.children("shape")
            if not refs or refs[0].attrs.get("type") != "shapegroup":
                raise SceneError("an instance needs a <ref> to a shapegroup", node.loc)
            group = refs[0]
            if id(group) not in self.groups:
                self.shape(group)
            self.flattened += len(self.groups[id(group)])
            if self.flattened > MAX_SHAPES:
                raise SceneError(f"instances flatten into more than {MAX_SHAPES} shapes",
                                 node.loc)
            out = []
            for s in self.groups[id(group)]:
                s = dict(s)
                s["to_world"] = (m @ np.asarray(s["to_world"])).tolist()
                out.append(s)
            obj.finish(("shape",))
            return out
        out: dict = {}
        bsdfs = obj.children("bsdf")
        if bsdfs:
            out["material"] = self.material(bsdfs[0])
            for extra in bsdfs[1:]:
                self.note(extra, "ignored: a shape has one bsdf, the first is used")
        else:
            if "default-diffuse" not in self.materials:
                self.materials["default-diffuse"] = {"type": "diffuse", "albedo": [0.5] * 3}
            out["material"] = "default-diffuse"
        for em in obj.children("emitter"):
            emitter = self.area_emitter(em)
            if emitter is not None:
                out["emitter"] = emitter
        for ch in obj.children("medium"):
            self.note(ch, "ignored: rayfarm renders no participating media")
        if self.materials[out["material"]]["type"] == "null":
            if "emitter" not in out:
                self.note(node, "left out: its null bsdf makes it invisible")
                for key in list(obj.props):
                    obj.ignore(key)
                obj.finish(("bsdf", "emitter", "medium", "texture"))
                return []
            black = f"{out['material']} (black)"
            self.materials[black] = {"type": "diffuse", "albedo": [0.0, 0.0, 0.0]}
            self.note(bsdfs[0], "approximated: an emitter with a null bsdf is a black diffuse "
                                "surface (it blocks the light that Mitsuba lets through it)")
            out["material"] = black
        if "emitter" in out and "opacity" in self.materials[out["material"]]:
            solid = f"{out['material']} (solid)"
            self.materials[solid] = {k: v for k, v in self.materials[out["material"]].items()
                                     if k not in ("opacity", "opacity_cutoff")}
            self.note(bsdfs[0], "approximated: the opacity mask of an emitting shape is "
                                "ignored, it renders solid (rayfarm's area lights have no masks)")
            out["material"] = solid
        if "id" in node.attrs:
            out["name"] = node.attrs["id"]
        flip = obj.bool("flip_normals", False)
        if t in ("rectangle", "cube", "disk"):
            out["type"] = t
            self._track_bounds([-1, -1, -1], [1, 1, 1], m)
        elif t == "sphere":
            center = obj.point("center", [0.0, 0.0, 0.0])
            radius = obj.float("radius", 1.0)
            mtm = m[:3, :3].T @ m[:3, :3]
            if not np.allclose(mtm, np.eye(3) * mtm[0, 0], rtol=1e-6, atol=1e-12):
                raise SceneError("a sphere's to_world must be a rotation, a uniform scale and a "
                                 "translation (Mitsuba refuses others too)", node.loc)
            out.update({"type": "sphere", "center": center, "radius": radius})
            self._track_bounds(np.subtract(center, radius), np.add(center, radius), m)
        elif t in ("obj", "ply", "serialized"):
            fname = obj.string("filename")
            if fname is None:
                raise SceneError(f"a {t} shape needs a filename", node.loc)
            path = self.find_file(fname, obj.props["filename"], "mesh file")
            shape_index = obj.int("shape_index", 0) if t == "serialized" else 0
            flip_uv = obj.bool("flip_tex_coords", True) if t == "obj" else False
            out["type"] = "mesh"
            digest, lo, hi, face_normals, notes = self._mesh(path, t, shape_index, flip_uv)
            out["mesh"] = digest
            self._track_bounds(lo, hi, m)
            for text in notes:
                self.note(obj.props["filename"], text)
            if obj.bool("face_normals", False) or face_normals:
                out["face_normals"] = True
            obj.ignore("max_smooth_angle", "ignored: the file's vertex normals are used as "
                                           "they are (rayfarm does not re-smooth)")
            obj.ignore("collapse", None)
        elif t == "cylinder":
            p0 = np.asarray(obj.point("p0", [0, 0, 0]), dtype=np.float64)
            p1 = np.asarray(obj.point("p1", [0, 0, 1]), dtype=np.float64)
            radius = obj.float("radius", 1.0)
            vertices, faces = self._cylinder(p0, p1, radius, node)
            out.update({"type": "mesh", "vertices": vertices, "faces": faces})
            self._track_bounds(np.min(vertices, axis=0), np.max(vertices, axis=0), m)
            self.note(node, f"approximated by a {CYLINDER_SEGMENTS}-sided open prism (rayfarm "
                            "has no analytic cylinder)")
        else:
            self.note(node, f"ignored: rayfarm has no '{t}' shape")
            for key in list(obj.props):
                obj.ignore(key)
            obj.finish(("bsdf", "emitter", "medium", "texture"))
            return []
        out["to_world"] = m.tolist()
        if flip:
            out["flip_normals"] = True
        if t in ("rectangle", "disk"):
            self.planar.append((out, node))
        obj.finish(("bsdf", "emitter", "medium"))
        return [out]

    def _cylinder(self, p0, p1, radius, node) -> tuple[list, list]:
        axis = p1 - p0
        if not np.linalg.norm(axis) > 0 or not radius > 0:
            raise SceneError("a cylinder needs p0 != p1 and a radius > 0", node.loc)
        w = axis / np.linalg.norm(axis)
        u = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(w, u)
        angles = np.linspace(0, 2 * math.pi, CYLINDER_SEGMENTS, endpoint=False)
        ring = radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
        vertices = np.concatenate([p0 + ring, p1 + ring])
        n = CYLINDER_SEGMENTS
        faces = []
        for k in range(n):
            a0, b0, a1, b1 = k, (k + 1) % n, n + k, n + (k + 1) % n
            faces += [[a0, b0, b1], [a0, b1, a1]]
        return vertices.tolist(), faces
