"""Scene importers: a scene file (and the folder around it) in, a native
rayfarm document and its assets out.

    imported = import_scene(Path("veach-bidir/scene.xml"))
    doc, assets = resolve_scene(imported.doc, assets=imported.assets)

`import_scene` dispatches on the suffix: ``.json`` is rayfarm's own format,
``.xml`` Mitsuba (renderer.importers.mitsuba), ``.gltf``/``.glb`` glTF 2.0
(renderer.importers.gltf). Every relative path a scene names must stay inside
`root` (default: the scene file's folder). `scene_name` names the scene
(an imported format has no name of its own). The document names meshes and
textures by digest; `assets` holds their blobs (renderer.assets). `report`
lists every element that is not rendered as written (approximated, ignored),
with its file and line: nothing a file asks for is dropped without an entry.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import SceneError

__all__ = ["Imported", "ReportEntry", "import_scene", "inside_root", "scene_name",
           "IMPORT_SUFFIXES"]

IMPORT_SUFFIXES = (".json", ".xml", ".gltf", ".glb")


@dataclass(frozen=True)
class ReportEntry:
    """One element not rendered as written: `element` e.g.
    ``bsdf type="roughplastic" id="Floor"``, `file` relative to the root,
    `line` (None where a format has none), `action` e.g. ``approximated as
    diffuse (reflectance = diffuseReflectance)`` or ``ignored``."""

    element: str
    file: str
    line: int | None
    action: str

    def to_dict(self) -> dict:
        return {"element": self.element, "file": self.file, "line": self.line,
                "action": self.action}

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line is not None else self.file
        return f"{where}: {self.element}: {self.action}"


@dataclass
class Imported:
    """A native document (meshes and textures by digest), its asset blobs by
    digest, and the import report."""

    doc: dict
    assets: dict[str, bytes] = field(default_factory=dict)
    report: list[ReportEntry] = field(default_factory=list)


def inside_root(root: Path, relative: str, where: str = "") -> Path:
    """`relative` (a path a scene file names, with / or \\ separators) resolved
    under `root`; refused if it is absolute or leaves `root` (also through a
    symbolic link)."""
    rel = str(relative).replace("\\", "/")
    if not rel or rel.startswith("/") or (len(rel) > 1 and rel[1] == ":"):
        raise SceneError(f"path '{str(relative)[:80]}' must be relative to the scene's folder",
                         where)
    base = Path(root).resolve()
    target = (base / rel).resolve()
    if target != base and base not in target.parents:
        raise SceneError(f"path '{str(relative)[:80]}' leaves the scene's folder", where)
    return target


def scene_name(path: Path, root: Path | None = None, root_name: str | None = None) -> str:
    """What the scene file `path` is called: its stem (``cbox`` for
    cbox.xml), but a file called just ``scene`` (veach-bidir/scene.xml, as
    scene collections name theirs) takes its folder's name. `root_name` is
    what the folder `root` stands for when its directory's own name is not
    the user's (an upload unpacked into the service's folder): an archive's
    name, or "" when no name came with the files (then the stem).

        scene_name(Path("veach-bidir/scene.xml"))                  # 'veach-bidir'
        scene_name(tree / "scene.xml", tree, root_name="")         # 'scene'
    """
    path = Path(path)
    stem = path.stem
    if stem != "scene":
        return stem
    folder = path.resolve().parent  # `rayfarm render scene.xml` inside the folder: its name
    root = Path(root) if root is not None else path.parent
    if root_name is not None and folder == root.resolve():
        name = root_name
    else:
        name = folder.name
    return name.lstrip(".") or stem  # a hidden folder's name as `rayfarm upload` zips it


def import_scene(path: Path, root: Path | None = None, root_name: str | None = None
                 ) -> Imported:
    """Import the scene file `path`; relative paths stay inside `root`. An
    imported format's document is named by `scene_name` (`root_name` see
    there); a rayfarm JSON document keeps the name it holds."""
    path = Path(path)
    root = Path(root) if root is not None else path.parent
    suffix = path.suffix.lower()
    if suffix not in IMPORT_SUFFIXES:
        raise SceneError(f"unknown scene file type '{path.suffix}' (allowed: "
                         f"{', '.join(IMPORT_SUFFIXES)})", path.name)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path.name}", path.name)
    if suffix == ".json":
        return _import_native(path, root)
    if suffix == ".xml":
        imported = _importer("mitsuba", "import_mitsuba", "Mitsuba XML", path)(path, root)
    else:
        imported = _importer("gltf", "import_gltf", "glTF", path)(path, root)
    imported.doc["name"] = scene_name(path, root, root_name)
    return imported


def _importer(module: str, name: str, what: str, path: Path):
    """An importer's entry point, imported lazily (each importer is optional)."""
    import importlib

    try:
        return getattr(importlib.import_module(f"{__name__}.{module}"), name)
    except ModuleNotFoundError as exc:
        if exc.name != f"{__name__}.{module}":
            raise
        raise SceneError(f"{what} scenes cannot be imported by this build", path.name) from None


def _import_native(path: Path, root: Path) -> Imported:
    """A rayfarm JSON scene: its mesh files become assets, named by digest."""
    from ..scene_format import MAX_FILE_BYTES, MAX_NESTING, _nesting, resolve_scene

    if path.stat().st_size > MAX_FILE_BYTES:
        raise SceneError("scene file too large", path.name)
    try:
        doc = json.loads(path.read_text())
    except UnicodeDecodeError:
        raise SceneError(f"{path.name} is not a text file", path.name) from None
    except json.JSONDecodeError as exc:
        raise SceneError(f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}",
                         f"{path.name}:{exc.lineno}") from None
    except RecursionError:
        raise SceneError(f"{path.name} is nested too deeply", path.name) from None
    if isinstance(doc, (dict, list)) and _nesting(doc) > MAX_NESTING:
        raise SceneError(f"{path.name} nests lists and objects more than {MAX_NESTING} levels "
                         "deep", path.name)
    base = path.parent
    if Path(root).resolve() not in (base.resolve(), *base.resolve().parents):
        raise SceneError("the scene file lies outside its root folder", path.name)
    doc, assets = resolve_scene(doc, base_dir=base, root=root)
    return Imported(doc=doc, assets=assets, report=[])
