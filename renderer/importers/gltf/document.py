"""The importer: the file checked as a whole, its scene walked, a native
document made of what the other modules read."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .. import Imported
from .meshes import _Meshes
from .scene_graph import _SceneGraph

# Extensions this importer renders (or maps, as the report says); a file that
# *requires* any other is refused naming it.
SUPPORTED_EXTENSIONS = frozenset({
    "KHR_lights_punctual", "KHR_materials_emissive_strength", "KHR_materials_transmission",
    "KHR_materials_ior", "KHR_texture_transform", "KHR_mesh_quantization",
})
MAX_SHAPES = 100_000  # mesh primitives placed by nodes


def import_gltf(path: Path, root: Path | None = None) -> Imported:
    """Import a `.gltf` or `.glb` file; every relative URI must stay inside
    `root` (default: the file's folder)."""
    path = Path(path)
    root = Path(root) if root is not None else path.parent
    return _Importer(path, root).run()


class _Importer(_Meshes, _SceneGraph):
    def run(self) -> Imported:
        self.load()
        g = self.gltf
        asset = self.obj(self.get(g, "asset", "", "obj", required=True), "/asset")
        version = self.get(asset, "version", "/asset", "str", required=True)
        if not version.startswith("2."):
            raise self.fail(f"glTF version {version} (this importer reads 2.x)", "/asset/version")
        min_version = self.get(asset, "minVersion", "/asset", "str")
        if min_version is not None and min_version not in ("2.0",):
            raise self.fail(f"the file needs glTF {min_version} (this importer reads 2.0)",
                            "/asset/minVersion")
        required = self.get(g, "extensionsRequired", "", "list", default=[])
        for k, name in enumerate(required):
            if name not in SUPPORTED_EXTENSIONS:
                raise self.fail(f"the file requires extension {name}, which this importer does "
                                f"not support (supported: {', '.join(sorted(SUPPORTED_EXTENSIONS))})",
                                f"/extensionsRequired/{k}")
        used = self.get(g, "extensionsUsed", "", "list", default=[])
        for name in used:
            if name not in SUPPORTED_EXTENSIONS:
                self.note("/extensionsUsed", f"extension {name} ignored", str(name))
        self.quantized = "KHR_mesh_quantization" in used or "KHR_mesh_quantization" in required
        for what in ("animations", "skins"):
            if self.array(what):
                self.note(f"/{what}", "ignored: the scene is rendered at rest, every node "
                          "with its own transform" if what == "animations" else
                          "ignored: skinned meshes are rendered in their bind pose")
        lights = self.punctual_lights()

        roots, sptr = self.scene_roots()
        shapes: list[dict] = []
        emitters: list[dict] = []
        camera: dict | None = None
        camera_ptr = ""
        for node, world, nptr in self.walk(roots, sptr):
            n = self.obj(self.array("nodes")[node], nptr)
            if "mesh" in n:
                shapes.extend(self.place_mesh(self.index(n, "mesh", nptr, "meshes"), world,
                                              n, nptr))
            if "camera" in n:
                ci = self.index(n, "camera", nptr, "cameras")
                c, cptr = self.item("cameras", ci)
                ctype = self.get(c, "type", cptr, "str", required=True)
                if ctype == "perspective" and camera is None:
                    camera, camera_ptr = self.camera(c, cptr, world, nptr), cptr
                elif ctype == "perspective":
                    self.note(cptr, f"ignored: the first perspective camera ({camera_ptr}) "
                              "is the one rendered", f"(at {nptr})")
                else:
                    self.note(cptr, f"ignored: {ctype} cameras are not rendered", f"(at {nptr})")
            light = self.extension(n, nptr, "KHR_lights_punctual")
            if light is not None:
                li = self.get(light, "light", f"{nptr}/extensions/KHR_lights_punctual", "int",
                              required=True)
                if li not in lights:
                    raise self.fail(f"light {li} does not exist",
                                    f"{nptr}/extensions/KHR_lights_punctual/light")
                em = lights[li](world, nptr)
                if em is not None:
                    emitters.append(em)
            self.other_extensions(n, nptr, ("KHR_lights_punctual",), "")
            if len(shapes) > MAX_SHAPES:
                raise self.fail(f"the scene places more than {MAX_SHAPES} mesh primitives",
                                nptr)
        if not shapes:
            skipped = sorted(self.skipped_modes)
            raise self.fail("the scene has no triangles to render" + (
                f": its primitives are {', '.join(skipped)}, which rayfarm does not render "
                "(only surfaces)" if skipped else ""), sptr or "/")
        if camera is None:
            camera = self.default_camera(shapes)
            self.note("/cameras", "no perspective camera in the scene: a default camera frames "
                      "the scene's bounds from +z (docs/scene-format.md, glTF 2.0)")
        if not emitters and not any("emitter" in s for s in shapes):
            self.note("/", "the scene has no lights (glTF viewers add their own): it renders "
                      "black unless lights are added")
        for s in shapes:
            s.pop("_bounds", None)
        materials = {name: mat for name, mat, _, _ in self.materials.values()}
        doc: dict[str, Any] = {
            "description": _description(asset, self.path.name),  # not where in the root
            "camera": camera,
            "materials": materials,
            "shapes": shapes,
        }
        if emitters:
            doc["emitters"] = emitters
        if self.textures:
            doc["textures"] = self.textures
        return Imported(doc=doc, assets=self.assets, report=self.report)


def _description(asset: dict, name: str) -> str:
    parts = [f"glTF 2.0 scene {name}"]
    for key in ("generator", "copyright"):
        if isinstance(asset.get(key), str):
            parts.append(f"{key}: {asset[key][:300]}")
    return "; ".join(parts)
