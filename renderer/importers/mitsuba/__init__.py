"""Mitsuba XML scenes (the 0.5/0.6 dialect and the 2.x/3.x one) in.

    imported = import_mitsuba(Path("veach-bidir/scene.xml"))

The file is read with expat (line numbers for every element; DOCTYPE and
entity declarations refused, so no entity expansion and no external
entities), `<include>`s are spliced in, `$name`s substituted from the
`<default>`s, and property names of the old dialect (`toWorld`, `intIOR`)
turned into the new one (`to_world`, `int_ior`) as Mitsuba 3 upgrades them.
Then each object maps onto the native document: what rayfarm renders as
written maps silently; what it approximates or ignores gets a `ReportEntry`
naming the element, its file and line, and what was done instead.
docs/scene-format.md ("Mitsuba XML") has the whole mapping.

Refusals are `SceneError`s located at "file:line".

The modules, each importing only those before it: `xmltree` (reading,
includes, defaults, refs, the report), `values` (properties, colours and
spectra, transforms), `textures`, `bsdfs`, `shapes`, `emitters`, `sensor`
(camera, film, filter), and `scene`, whose importer joins them.
"""

from __future__ import annotations

from .scene import UNBOUNDED_DEPTH, _Importer, import_mitsuba
from .shapes import MAX_SHAPES
from .values import look_at
from .xmltree import MAX_ELEMENTS, MAX_INCLUDE_DEPTH, MAX_NESTING, MAX_REF_DEPTH, MAX_XML_BYTES

__all__ = ["import_mitsuba", "MAX_XML_BYTES", "MAX_ELEMENTS", "MAX_NESTING", "MAX_INCLUDE_DEPTH",
           "MAX_REF_DEPTH", "MAX_SHAPES", "UNBOUNDED_DEPTH"]
