"""Scene importers: a user's file tree in, a native document plus assets out.

Placeholder until the "assets" branch lands its dispatcher (contract section 2):
only the types the glTF importer returns, shaped as the contract says.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Imported", "ReportEntry", "import_scene"]


@dataclass(frozen=True)
class ReportEntry:
    element: str
    file: str
    line: int | None
    action: str


@dataclass
class Imported:
    doc: dict
    assets: dict[str, bytes] = field(default_factory=dict)
    report: list[ReportEntry] = field(default_factory=list)


def import_scene(path: Path, root: Path | None = None) -> Imported:
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".gltf", ".glb"):
        from .gltf import import_gltf
        return import_gltf(path, root)
    from ..errors import SceneError
    raise SceneError(f"unsupported scene file type '{suffix}'", path.name)
