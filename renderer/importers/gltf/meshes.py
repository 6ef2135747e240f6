"""Meshes: primitives read, triangulated and stored as mesh assets, placed
by the nodes that name them; emitting ones lose the triangles a light cannot
have."""

from __future__ import annotations

import numpy as np

from ...assets import asset_digest, encode_mesh
from ...scene_format import COLLINEAR, MAX_COORDINATE, MAX_TRIANGLES, MIN_EMITTER_AREA
from .accessors import _Accessors, _check_finite
from .materials import _Materials

MODES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES",
         5: "TRIANGLE_STRIP", 6: "TRIANGLE_FAN"}


class _Meshes(_Accessors, _Materials):
    # -- meshes ---------------------------------------------------------------

    def place_mesh(self, mi: int, world: np.ndarray, node: dict, nptr: str) -> list[dict]:
        mesh, mptr = self.item("meshes", mi)
        prims = self.get(mesh, "primitives", mptr, "list", required=True)
        if not prims:
            raise self.fail("a mesh needs at least one primitive", f"{mptr}/primitives")
        if self.get(mesh, "weights", mptr, "list") or "weights" in node:
            self.note(mptr, "morph target weights ignored: the base shape is rendered")
        if "skin" in node:
            self.note(nptr, "skin ignored: the mesh is rendered in its bind pose")
        if not np.all(np.isfinite(world)) or np.any(np.abs(world) > MAX_COORDINATE):
            raise self.fail(f"the node's world transform has entries beyond "
                            f"+-{MAX_COORDINATE:g}", nptr)
        if abs(np.linalg.det(world[:3, :3])) < 1e-12:
            self.note(nptr, "not rendered: its world transform is singular (a zero scale hides "
                      "it)")
            return []
        label = self.get(node, "name", nptr, "str") or self.get(mesh, "name", mptr, "str") or ""
        out = []
        for k in range(len(prims)):
            prim = self.primitive(mi, k)
            if prim is None:
                continue
            pptr = f"{mptr}/primitives/{k}"
            name, _, emission, _ = self.material(prim["material"])
            self.triangles += prim["triangles"]
            if self.triangles > MAX_TRIANGLES:
                raise self.fail(f"the scene has more than {MAX_TRIANGLES} triangles", pptr)
            shape = {"type": "mesh", "mesh": prim["digest"], "material": name,
                     "to_world": world.tolist(),
                     "name": f"{label or 'mesh ' + str(mi)}/{k}"}
            if emission is not None:
                digest = self.emitting_mesh(prim, world, pptr)
                if digest is None:
                    self.note(pptr, "emission ignored: none of its triangles has an area")
                else:
                    shape["mesh"] = digest
                    shape["emitter"] = {"type": "area", "radiance": emission}
            lo, hi = _world_bounds(prim["positions"], world)
            shape["_bounds"] = (lo, hi)
            out.append(shape)
        return out

    def primitive(self, mi: int, k: int) -> dict | None:
        """Mesh mi's primitive k in local space, encoded as an asset (cached)."""
        key = (mi, k)
        if key in self.meshes:
            return self.meshes[key]
        self.meshes[key] = None
        prim_raw = self.get(self.item("meshes", mi)[0], "primitives", f"/meshes/{mi}", "list")[k]
        ptr = f"/meshes/{mi}/primitives/{k}"
        p = self.obj(prim_raw, ptr)
        attrs = self.obj(self.get(p, "attributes", ptr, "obj", required=True), f"{ptr}/attributes")
        mode = self.get(p, "mode", ptr, "int", default=4)
        if mode not in MODES:
            raise self.fail(f"unknown primitive mode {mode}", f"{ptr}/mode")
        material = self.index(p, "material", ptr, "materials")
        if mode < 4:
            self.skipped_modes.add(MODES[mode])
            self.note(ptr, f"ignored: {MODES[mode]} have no area to render")
            return None
        if self.extension(p, ptr, "KHR_draco_mesh_compression") is not None:
            self.note(ptr, "KHR_draco_mesh_compression ignored: the uncompressed accessors "
                      "are read")
        self.other_extensions(p, ptr, ("KHR_draco_mesh_compression",), "")
        if p.get("targets"):
            self.note(ptr, "morph targets ignored: the base shape is rendered")
        for name in attrs:
            if name.startswith("COLOR_"):
                self.note(ptr, f"vertex colours ({name}) ignored")
        if "POSITION" not in attrs:
            raise self.fail("a primitive needs a POSITION attribute", f"{ptr}/attributes")
        floats = (5126,)
        quant_pos = (5120, 5121, 5122, 5123) if self.quantized else ()
        pos = self.accessor(self.index(attrs, "POSITION", f"{ptr}/attributes", "accessors"),
                            f"POSITION of {ptr}", ("VEC3",), floats + quant_pos
                            ).astype(np.float64)
        nv = len(pos)
        _check_finite(self, pos, attrs["POSITION"], "POSITION")
        if np.any(np.abs(pos) > MAX_COORDINATE):
            j = int(np.argmax(np.any(np.abs(pos) > MAX_COORDINATE, axis=1)))
            raise self.fail(f"vertex {j} lies at {pos[j].tolist()}; every coordinate must be "
                            f"within +-{MAX_COORDINATE:g}", f"/accessors/{attrs['POSITION']}")
        normals = None
        if "NORMAL" in attrs:
            ni = self.index(attrs, "NORMAL", f"{ptr}/attributes", "accessors")
            normals = self.accessor(ni, f"NORMAL of {ptr}", ("VEC3",),
                                    floats + ((5120, 5122) if self.quantized else ()))
            if normals.dtype != np.float64:
                raise self.fail("integer NORMAL must be normalized", f"/accessors/{ni}")
            self.same_count(normals, nv, ni, "NORMAL", ptr)
            length = np.linalg.norm(normals, axis=1)
            bad = ~np.isfinite(length) | (length < 1e-6)
            if np.any(bad):
                self.note(ptr, f"NORMAL ignored: {int(bad.sum())} of its {nv} normals are zero "
                          "or not finite; the geometric normals are used")
                normals = None
            else:
                normals = normals / length[:, None]
        uvs = None
        if "TEXCOORD_0" in attrs:
            ti = self.index(attrs, "TEXCOORD_0", f"{ptr}/attributes", "accessors")
            uvs = self.accessor(ti, f"TEXCOORD_0 of {ptr}", ("VEC2",),
                                floats + (5121, 5123) + ((5120, 5122) if self.quantized else ()))
            if uvs.dtype != np.float64 and not self.quantized:
                raise self.fail("integer TEXCOORD_0 must be normalized", f"/accessors/{ti}")
            uvs = uvs.astype(np.float64)
            self.same_count(uvs, nv, ti, "TEXCOORD_0", ptr)
            if not np.all(np.isfinite(uvs)):
                self.note(ptr, "TEXCOORD_0 ignored: it holds values that are not finite")
                uvs = None
        if "indices" in p:
            ii = self.index(p, "indices", ptr, "accessors")
            idx = self.accessor(ii, f"the indices of {ptr}", ("SCALAR",), (5121, 5123, 5125))
            if idx.dtype != np.int64:
                raise self.fail("indices must not be normalized", f"/accessors/{ii}/normalized")
            idx = idx[:, 0]
            if idx.size and idx.max() >= nv:
                j = int(np.argmax(idx >= nv))
                raise self.fail(f"index {j} is {int(idx[j])}, beyond the primitive's {nv} "
                                f"vertices", f"/accessors/{ii}")
        else:
            idx = np.arange(nv, dtype=np.int64)
        faces = self.triangulate(idx, mode, ptr)
        if len(faces) == 0:
            self.note(ptr, "ignored: it has no triangles")
            return None
        blob = encode_mesh(pos, faces, normals, uvs)
        digest = asset_digest(blob)
        self.assets[digest] = blob
        entry = {"digest": digest, "positions": pos, "faces": faces, "normals": normals,
                 "uvs": uvs, "material": material, "triangles": len(faces)}
        self.meshes[key] = entry
        return entry

    def same_count(self, arr: np.ndarray, nv: int, ai: int, what: str, ptr: str) -> None:
        if len(arr) != nv:
            raise self.fail(f"{what} has {len(arr)} elements but POSITION has {nv} (all "
                            f"attributes of {ptr} must have the same count)", f"/accessors/{ai}")

    def triangulate(self, idx: np.ndarray, mode: int, ptr: str) -> np.ndarray:
        n = len(idx)
        if mode == 4:
            if n % 3:
                self.note(ptr, f"the last {n % 3} vertices ignored: TRIANGLES needs a multiple "
                          f"of 3 ({n} given)")
            return idx[: n - n % 3].reshape(-1, 3)
        if n < 3:
            return np.zeros((0, 3), np.int64)
        i = np.arange(n - 2)
        if mode == 5:  # strip: every other triangle swaps two vertices to keep the winding
            odd = i % 2
            return np.stack([idx[i], idx[i + 1 + odd], idx[i + 2 - odd]], axis=1)
        return np.stack([idx[i + 1], idx[i + 2], np.full(n - 2, idx[0])], axis=1)  # fan

    def emitting_mesh(self, prim: dict, world: np.ndarray, ptr: str) -> str | None:
        """The primitive's asset without the triangles an area light cannot
        have (no area, or a sliver, in world space); None if none is left."""
        wv = prim["positions"] @ world[:3, :3].T + world[:3, 3]
        tri = wv[prim["faces"]]
        e1, e2, e3 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], tri[:, 2] - tri[:, 1]
        longest = np.max(np.linalg.norm(np.stack([e1, e2, e3], axis=1), axis=2), axis=1)
        double_area = np.linalg.norm(np.cross(e1, e2), axis=1)
        keep = (0.5 * double_area >= MIN_EMITTER_AREA) & (double_area >= COLLINEAR * longest ** 2)
        if keep.all():
            return prim["digest"]
        if not keep.any():
            return None
        self.note(ptr, f"{int((~keep).sum())} degenerate triangles left out of its area light")
        blob = encode_mesh(prim["positions"], prim["faces"][keep], prim["normals"], prim["uvs"])
        digest = asset_digest(blob)
        self.assets[digest] = blob
        return digest


def _world_bounds(positions: np.ndarray, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    wv = positions @ world[:3, :3].T + world[:3, 3]
    return wv.min(axis=0), wv.max(axis=0)
