"""Scene importers: a user's scene file (and the files it names) in, a native
rayfarm document plus its assets and an import report out.

    imported = import_scene(Path("scenes/room/scene.xml"))
    imported.doc      # a native document (docs/scene-format.md)
    imported.assets   # {digest: blob} for the meshes and textures it names
    imported.report   # [ReportEntry]: what is not rendered as written

`import_scene` dispatches on the suffix: `.json` native, `.xml` Mitsuba,
`.gltf`/`.glb` glTF. `root` is the folder every relative path must stay
inside (default: the scene file's folder).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..errors import SceneError

__all__ = ["Imported", "ReportEntry", "import_scene"]


@dataclass(frozen=True)
class ReportEntry:
    """One thing a scene file asks for that is not rendered as written."""

    element: str  # e.g. 'bsdf type="roughplastic" id="Floor"'
    file: str  # relative to the import's root
    line: int | None
    action: str  # e.g. 'approximated as diffuse (reflectance = diffuse_reflectance)'

    def as_dict(self) -> dict:
        return {"element": self.element, "file": self.file, "line": self.line,
                "action": self.action}

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line is not None else self.file
        return f"{where}: {self.element}: {self.action}"


@dataclass
class Imported:
    doc: dict
    assets: dict[str, bytes] = field(default_factory=dict)
    report: list[ReportEntry] = field(default_factory=list)


def import_scene(path: Path, root: Path | None = None) -> Imported:
    """Import the scene file at `path` (see the module doc)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".xml":
        from .mitsuba import import_mitsuba

        return import_mitsuba(path, root)
    if suffix in (".gltf", ".glb"):
        from .gltf import import_gltf  # type: ignore[import-not-found]

        return import_gltf(path, root)
    if suffix == ".json":
        import json

        try:
            doc = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise SceneError(f"cannot read {path.name}: {exc}") from None
        return Imported(doc=doc)
    raise SceneError(f"unknown scene file type '{path.suffix}' "
                     "(allowed: .json, .xml, .gltf, .glb)")
