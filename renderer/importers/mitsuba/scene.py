"""The importer: a scene element's children mapped onto the native
document (the bases map each kind of object), the integrator's depth as its
default, and the report in file order."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import SceneError
from ...primitives import world_mesh
from .. import Imported, ReportEntry
from .bsdfs import BsdfMapper
from .emitters import EmitterMapper
from .sensor import SensorMapper
from .shapes import ShapeMapper
from .textures import TextureMapper
from .values import _Obj, ValueReader
from .xmltree import MAX_REF_DEPTH, _Node, _parse_xml, XmlTree

# Mitsuba's max_depth -1 means unbounded; a job takes at most 64 bounces (spec.py).
UNBOUNDED_DEPTH = 64


class _Importer(XmlTree, ValueReader, TextureMapper, BsdfMapper, ShapeMapper, EmitterMapper,
                SensorMapper):
    def __init__(self, path: Path, root: Path | None):
        self.path = Path(path)
        self.root = Path(root if root is not None else self.path.parent).resolve()
        self.main = self.path.resolve()
        if not self.main.is_relative_to(self.root):
            raise SceneError("the scene file lies outside its root folder", self.path.name)
        self.report: list[ReportEntry] = []
        self.params: dict[str, str] = {}
        self.include_stack: list[Path] = []
        self.elements = 0
        self.ids: dict[str, _Node] = {}
        self.assets: dict[str, bytes] = {}
        self.materials: dict[str, dict] = {}
        self.material_of: dict[int, str] = {}
        self.textures: dict[str, dict] = {}
        self.texture_of: dict[int, object] = {}
        self.mesh_cache: dict[tuple, tuple] = {}
        self.texture_cache: dict[tuple, str] = {}
        self.map_stack: list[_Node] = []
        self.bounds: list[np.ndarray] = []
        self.groups: dict[int, list[dict]] = {}
        self.planar: list[tuple[dict, _Node]] = []  # rectangles and disks, to check their sides
        self.flattened = 0  # shapes instances have copied

    # -- integrator ------------------------------------------------------------------------
    def integrator(self, node: _Node) -> int:
        """Rayfarm's default depth (bounces) from the block's max_depth."""
        found: list[tuple[int, _Node]] = []

        def walk(n: _Node, depth: int = 0) -> None:
            if depth > MAX_REF_DEPTH:
                return
            o = _Obj(self, n)
            if o.has("max_depth"):
                p = o.props["max_depth"]
                try:
                    found.append((o.int("max_depth"), p))
                except SceneError:
                    self.note(p, "ignored: max_depth is not an integer")
            for ch in o.children("integrator"):
                walk(ch, depth + 1)
            for key in list(o.props):
                if key != "max_depth":
                    o.ignore(key, "ignored: the job's method and options decide")

        try:
            walk(node)
        except SceneError as exc:  # an integrator block is never a reason to refuse the file
            self.note(node, f"ignored ({exc}): the default depth is capped at "
                            f"{UNBOUNDED_DEPTH} bounces")
            return UNBOUNDED_DEPTH
        t = node.attrs.get("type", "")
        if not found:
            self.note(node, f"its type '{t}' is not used (the job's method decides how to "
                            f"render); no max_depth: Mitsuba's unbounded depth is capped at "
                            f"{UNBOUNDED_DEPTH} bounces")
            return UNBOUNDED_DEPTH
        depth, p = found[0]
        if depth < 0:
            bounces = UNBOUNDED_DEPTH
            how = f"max_depth {depth} (unbounded) -> at most {UNBOUNDED_DEPTH} bounces"
        else:
            bounces = min(max(depth - 1, 0), UNBOUNDED_DEPTH)
            how = f"max_depth {depth} -> depth {bounces} (bounces: Mitsuba's max_depth - 1)"
            if depth - 1 > UNBOUNDED_DEPTH:
                how += f", capped at {UNBOUNDED_DEPTH}"
            if depth == 0:
                how += " (Mitsuba renders nothing at max_depth 0; rayfarm shows the emitters)"
        self.note(node, f"its type '{t}' is not used (the job's method decides how to "
                        f"render); the default depth comes from {how}")
        return bounces

    # -- the scene -------------------------------------------------------------------------
    def run(self) -> Imported:
        top = _parse_xml(self.main, self.rel(self.main))
        if top.tag != "scene":
            raise SceneError(f"the root element must be <scene>, not <{top.tag}>", top.loc)
        scene = self.expand(top)[0]
        cameras, shapes, emitters = [], [], []
        depth = None
        for node in scene.children:
            tag = node.tag
            if tag == "sensor":
                if cameras:
                    self.note(node, "ignored: rayfarm renders the first sensor")
                else:
                    cameras.append(self.camera(node))
            elif tag == "integrator":
                if depth is not None:
                    self.note(node, "ignored: only the first integrator gives defaults")
                else:
                    depth = self.integrator(node)
            elif tag == "shape":
                shapes.extend(self.shape(node))
            elif tag == "emitter":
                em = self.emitter(node)
                if em is not None:
                    emitters.append(em)
            elif tag in ("bsdf", "texture"):
                if "id" not in node.attrs:
                    self.note(node, f"ignored: a {tag} at the top level without an id is never "
                                    "used")
            elif tag in ("medium", "phase", "volume"):
                self.note(node, "ignored: rayfarm renders no participating media")
            elif tag == "ref":
                self.note(node, "ignored: a reference at the top level has no effect")
            else:
                self.note(node, f"ignored (<{tag}> is not an element rayfarm reads at the top "
                                "level of a scene)")
        if depth is None:
            depth = UNBOUNDED_DEPTH
            self.note(scene, f"no integrator: Mitsuba's default path tracer is unbounded; the "
                             f"default depth is capped at {UNBOUNDED_DEPTH} bounces")
        if not cameras:
            cameras.append(self.default_camera(scene))
        self.materials = {k: v for k, v in self.materials.items() if v["type"] != "null"}
        self.check_sides(cameras[0])
        doc: dict = {"camera": cameras[0], "materials": self.materials,
                     "shapes": shapes, "emitters": emitters, "defaults": {"max_depth": depth}}
        if self.textures:
            doc["textures"] = self.textures
        main = self.rel(self.main)  # the report in file order: the main file's first
        self.report.sort(key=lambda e: (e.file != main, e.file, e.line or 0))
        return Imported(doc=doc, assets=self.assets, report=self.report)

    def check_sides(self, camera: dict) -> None:
        """Say where a one-sided rectangle or disk turns its back to the
        camera: Mitsuba renders it black from there, and so does rayfarm."""
        eye = np.asarray(camera["to_world"])[:3, 3]
        for shape, node in self.planar:
            mat = self.materials[shape["material"]]
            if mat.get("twosided") or mat["type"] == "dielectric":
                continue
            vertices, faces = world_mesh(shape)
            a, b, c = vertices[faces[0]]
            normal = np.cross(b - a, c - a)
            if np.dot(normal, eye - vertices.mean(axis=0)) < 0:
                self.note(node, f"its material '{shape['material']}' is one-sided and the camera "
                                "sees its back: it renders black there (as in Mitsuba; wrap the "
                                "bsdf in twosided to light both sides)")


def import_mitsuba(path: Path, root: Path | None = None) -> Imported:
    """Import a Mitsuba XML scene (see the module doc). `root` is the folder
    every file it names must lie in (default: the scene file's folder)."""
    try:
        return _Importer(Path(path), root).run()
    except RecursionError:
        raise SceneError("the scene nests too deeply", Path(path).name) from None
