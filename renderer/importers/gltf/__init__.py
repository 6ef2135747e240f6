"""glTF 2.0 importer: a `.gltf` (JSON, with its buffers and images by relative
URI or as base64 `data:` URIs) or a `.glb` (the binary container) in, a
native rayfarm document plus its assets out.

    imported = import_gltf(Path("models/box.glb"))   # -> Imported(doc, assets, report)

Everything the file holds is validated before it is used: the JSON's types,
indices into every array, accessors against their buffer views and buffers,
component types and normalized flags, the node hierarchy (a forest of strict
trees, bounded depth; cycles refused). Refusals are `SceneError`s whose
location is a JSON pointer into the file (``box.gltf#/accessors/3``).
What the file asks for that rayfarm does not render as written goes into the
import report. docs/scene-format.md ("glTF 2.0") documents the mapping.

The work is bounded: the file, every buffer and image are read at most once
and only when used; triangles, shapes and node depth have limits, so a hostile
file is refused before it costs memory or time.

The modules, each a layer of the importer (each imports only modules
named before it): reader (state, errors, the report, typed JSON access),
container (.gltf/.glb, buffers, URIs, buffer views), accessors,
materials (materials and their textures), meshes (primitives placed by
nodes), scene_graph (nodes, cameras, lights), document (the native
document they make).
"""

from __future__ import annotations

from ...assets import asset_digest, encode_mesh, encode_texture
from .container import CHUNK_BIN, CHUNK_JSON, GLB_MAGIC
from .document import SUPPORTED_EXTENSIONS, _Importer, import_gltf
from .scene_graph import POINT_CANDELA_PER_WATT_SR

__all__ = ["import_gltf", "SUPPORTED_EXTENSIONS", "POINT_CANDELA_PER_WATT_SR"]
